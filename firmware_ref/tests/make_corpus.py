"""Seed corpus for the decoder fuzzer: every golden vector (serial frames without the delimiter,
CAN frames as id LE + flags + data) and a few chip scripts. Run from the repo root:

    .venv/bin/python firmware_ref/tests/make_corpus.py

`make -C firmware_ref fuzz` grows build/corpus from these; `make -C firmware_ref asan` and the
pytest suite replay tests/corpus under ASan/UBSan.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = Path(__file__).resolve().parent / "corpus"


def main() -> None:
    OUT.mkdir(exist_ok=True)
    vec = ROOT / "tests" / "vectors"
    for v in json.loads((vec / "serial.json").read_text())["vectors"]:
        (OUT / f"serial_{v['name']}").write_bytes(bytes.fromhex(v["hex"])[:-1])
    for v in json.loads((vec / "serial_errors.json").read_text())["vectors"]:
        (OUT / f"error_{v['name']}").write_bytes(bytes.fromhex(v["hex"]))
    for v in json.loads((vec / "can.json").read_text())["vectors"]:
        flags = 1 | (2 if v["fd"] else 0) | 4
        (OUT / f"can_{v['name']}").write_bytes(struct.pack("<IB", int(v["id"], 16), flags) + bytes.fromhex(v["data"]))
    # chip scripts: [fault/cfg][caps] then steps [op][node sel][type][len][payload]
    uid_low = struct.pack("<I", 0x89ABCDEF)
    assign = bytes([0x00, 0x01, 0x11, 8]) + struct.pack("<HH", 5, 3) + uid_low
    config = bytes([0x04, 0x01, 0x12, 6]) + struct.pack("<HBBH", 145, 0, 0, 100)
    start = bytes([0x04, 0x01, 0x13, 0])
    sync = b"".join(bytes([0x04, 0x00, 0x10, 2]) + struct.pack("<H", c) for c in (1, 2, 5, 0xFFFF, 0))
    calw = bytes([0x00, 0x01, 0x17, 8]) + struct.pack("<BBhf", 1, 1, -3, 1000.0)
    calr = bytes([0x00, 0x01, 0x18, 1, 1])
    reset = bytes([0x00, 0x01, 0x16, 0])
    (OUT / "script_lifecycle").write_bytes(bytes([0, 0x10]) + assign + config + calw + calr + start + sync + reset)
    (OUT / "script_fault").write_bytes(bytes([7, 0x3F]) + assign + start + sync + calr)


if __name__ == "__main__":
    main()
