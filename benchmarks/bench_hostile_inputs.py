"""Memory and time under hostile input (docs/distribution.md "Payload checks", docs/recording.md "A
file someone sent you"). Prints JSON:

* ``worker_flood``: ``capsheet estimate --subscribe`` while 400 junk payloads of 1 MiB arrive for a
  sheet whose info never answers, and while 200 well-formed 1 MB snapshots do: the worker's peak
  RSS (kernel figure, ``RUSAGE_CHILDREN`` of a wrapper) and what it counted;
* ``crafted_files``: every file of tests/host/record/crafted.py through every command that reads
  it (tests/host/record/refuse_driver.py): the largest peak RSS, the longest time, and any that
  was not refused in one line.

    .venv/bin/python benchmarks/bench_hostile_inputs.py [--skip-flood] [--skip-files]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def worker_flood() -> dict:
    import numpy as np

    from tests.host.cli.test_received_payloads import _run_worker_flooded, _tag, _worker_snapshot

    rng = np.random.Generator(np.random.MT19937(49))
    junk = [rng.integers(0, 256, 1 << 20, dtype=np.uint8).tobytes() for _ in range(8)]
    out = {}
    for name, payloads in (("junk_400_x_1MiB", [junk[k % 8] for k in range(400)]),
                           ("snapshots_200_x_1MB", [_worker_snapshot(2, 8322)] * 200)):
        sheet = _tag()
        doc, rss_mb, _err = _run_worker_flooded(payloads, sheet)
        (d,) = [d for d in doc["sheets"] if d["sheet"] == sheet]
        out[name] = {"peak_rss_mb": round(rss_mb, 1), "received": d["received"],
                     "bad_payloads": d.get("bad_payloads", 0), "dropped_waiting": d.get("dropped_waiting", 0),
                     "exit": doc["exit"]}
    return out


def crafted_files() -> dict:
    from tests.host.record.crafted import argv, corpus
    from tests.host.record.test_untrusted_files import _drive

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        files = corpus(folder / "in")
        (folder / "out").mkdir()
        commands = [[name, a] for name, (p, kind) in files.items() for a in argv(p, kind, folder / "out")]
        got = _drive(commands, folder)
    rows = list(got.values())
    worst = max(rows, key=lambda r: r["maxrss_mb"])
    slowest = max(rows, key=lambda r: r["seconds"])
    not_one_line = [r["name"] for r in rows if len([x for x in r["stderr"].splitlines() if x.strip()]) != 1
                    or "Traceback" in r["stderr"] or r["exit"] not in (1, 2)]
    return {"commands": len(rows), "files": len(files), "max_peak_rss_mb": worst["maxrss_mb"],
            "max_peak_rss_of": f"{worst['name']} ({worst['argv'][0]})", "max_seconds": slowest["seconds"],
            "max_seconds_of": f"{slowest['name']} ({slowest['argv'][0]})", "not_refused_in_one_line": not_one_line}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--skip-flood", action="store_true")
    ap.add_argument("--skip-files", action="store_true")
    a = ap.parse_args()
    out = {}
    if not a.skip_flood:
        out["worker_flood"] = worker_flood()
    if not a.skip_files:
        out["crafted_files"] = crafted_files()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
