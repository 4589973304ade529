"""The part chips' wire bytes, frozen: what seeded ``--firmware c --part ...`` sheets emit on a
simulated clock is byte for byte what the emulators and their glue emitted when this file's golden
data was recorded.

Why a golden file: the register emulators (virtual_sheet/parts/) and their glue (firmware_ref/
part_chip.py, sil_bus.py) are written for speed (plain floats, bytearray register banks, burst
reads); a faster emulator must be the same emulator. Every noise draw, rounding, SET/RESET offset
step, data-ready edge and self-test result reaches the frames, so one changed value anywhere shows
here as the first SYNC whose bytes differ. What each value should be is tested against the
datasheets elsewhere (tests/virtual_sheet/parts/, test_driver_*.py, test_part_chip.py); this file
only says the values did not move.

The golden data (part_frames_golden.json, beside this file) was recorded from the emulators before
they were made faster. Regenerate it only for a change that is meant to change what the parts
answer (and say so in the commit)::

    .venv/bin/python -m tests.firmware_ref.test_part_frames_same --write

The magnetometer's field goes through numpy's ``@`` (a BLAS call): the recorded bytes are those of
this machine's numpy and BLAS build; another BLAS may round a field's last bit differently.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol.framing import encode
from protocol.messages import ConfigImu, Start, Sync
from virtual_sheet.gateway import Gateway
from virtual_sheet.sheet import VirtualSheet

GOLDEN = Path(__file__).with_name("part_frames_golden.json")

#: name -> (part, sensors, shape, lattice, seed, CONFIG_IMU format, SYNCs): a moving 9-axis sheet (the
#: field and the motion change every SYNC) and a resting 6-axis one
CASES = {
    "9axis_wave_3x3": ("icm42688p+mmc5983ma", "accel+gyro+mag", "wave", "3x3", 11, 2, 40),
    "6axis_gaussian_3x3": ("icm42688p", "accel+gyro", "gaussian", "3x3", 6, 1, 40),
}


def record(name: str) -> list[str]:
    """The wire bytes (hex) of one case: the bring-up's, then each SYNC's, on a simulated clock."""
    from host.cli.virtual import part_chip_factory
    part, sensors, shape, lattice, seed, fmt, n_syncs = CASES[name]
    fac = part_chip_factory(part)
    sheet = VirtualSheet(shape, lattice, seed=seed, chip_factory=fac, sensors=sensors)
    fac.bind(sheet)
    gw = Gateway(sheet, packed=False)
    gw.power_on(0.0)
    gw.commission(0.1, start=False)
    gw.feed(encode(ConfigImu(0, format=fmt, gyro_range=3)), 0.2)
    gw.feed(encode(Start(0)), 0.3)
    for t in np.arange(0.3, 2.0, 0.01):          # the chips' timers and main loops
        gw.poll(float(t))
    out = [gw.pop_bytes(2.0).hex()]
    for i in range(n_syncs):
        now = 2.0 + 0.01 * i                       # 100 SYNC/s
        gw.feed(encode(Sync(counter=i)), now)
        gw.poll(now)
        out.append(gw.pop_bytes(now + 0.005).hex())
    return out


def first_difference(got: list[str], want: list[str]) -> str | None:
    for k, (g, w) in enumerate(zip(got, want)):
        if g != w:
            at = next(i for i in range(min(len(g), len(w)) + 1) if g[i:i + 2] != w[i:i + 2]) // 2
            where = "the bring-up" if k == 0 else f"SYNC {k - 1}"
            return f"{where}: first differing byte at offset {at} (of {len(w) // 2})"
    if len(got) != len(want):
        return f"{len(got)} SYNCs recorded, {len(want)} in the golden file"
    return None


@pytest.mark.parametrize("name", sorted(CASES))
def test_part_sheet_frames_are_byte_for_byte_the_recorded_ones(name):
    pytest.importorskip("firmware_ref.part_chip")
    want = json.loads(GOLDEN.read_text())["cases"][name]
    got = record(name)
    assert sum(len(s) for s in got[1:]) > 0, "no frames at all: the sheet did not stream"
    assert all(got[1:]), "a SYNC with no frame"
    assert first_difference(got, want) is None, first_difference(got, want)


def main(argv: list[str]) -> int:
    if argv != ["--write"]:
        print("usage: python -m tests.firmware_ref.test_part_frames_same --write", file=sys.stderr)
        return 2
    doc = {"how": "python -m tests.firmware_ref.test_part_frames_same --write (see the test's docstring)",
           "cases": {name: record(name) for name in sorted(CASES)}}
    GOLDEN.write_text(json.dumps(doc, indent=0) + "\n")
    print(f"wrote {GOLDEN} ({GOLDEN.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
