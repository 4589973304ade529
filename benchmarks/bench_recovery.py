"""How long a host takes to recover a sheet that was power-cycled under the same port.

Each run: ``capsheet virtual`` (a subprocess) streams to ``capsheet host`` (another subprocess); the
sheet is stopped (SIGTERM: its port goes away), restarted on the same symlink, and the host has to
reconnect, re-assign, re-configure, re-read calibration and restart every chip by itself.

Measured (CLOCK_MONOTONIC is one clock for every process on Linux, so the host's event times and
this script's observations compare directly):

* ``recovered_s``: from the moment the new sheet's port exists to the host's "recovery" report
  (every chip streaming again). Goal: < 2 s.
* ``first_complete_s``: from the same moment to the first complete snapshot in the host's recording.
* ``complete_after_pct``: complete snapshots after the recovery report, of all after it;
  ``complete_before_pct`` the same before the sheet was stopped (what this machine sustains at all).

Prints JSON. ``--quick`` runs one repetition of the small configurations.

    python benchmarks/bench_recovery.py [--reps 3] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CLI = [sys.executable, "-m", "host.cli"]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


def _virtual(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(CLI + ["virtual", *args], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, env=ENV, cwd=ROOT)


def _host_cmd(v: subprocess.Popen) -> list[str]:
    for line in v.stdout:
        if line.strip().startswith("capsheet host "):
            threading.Thread(target=lambda: [None for _ in v.stdout], daemon=True).start()  # keep draining
            return line.split()[2:]
    raise RuntimeError("capsheet virtual printed no host command")


def one_run(transport: str, lattice: str, sync: str, rate: float) -> dict:
    from host.record.recording import read_recording
    import numpy as np
    tmp = Path(tempfile.mkdtemp(prefix="bench-recovery-"))
    port, lay, rec = tmp / "port", tmp / "sheet.csv", tmp / "run.mcap"
    vargs = ["--lattice", lattice, "--transport", transport, "--symlink", str(port), "--layout-out", str(lay)]
    if sync == "follow":
        vargs += ["--rate", f"{rate:g}"]
    a = _virtual(vargs)
    cmd = _host_cmd(a)
    if sync != "follow":
        cmd += ["--rate", f"{rate:g}"]
    h = subprocess.Popen(CLI + ["host", *cmd, "--duration", "120", "--json", "-q", "--record", str(rec),
                                "--deadline-ms", "300"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    lines: list[str] = []
    started, recovered = threading.Event(), threading.Event()

    def read_err():
        for line in h.stderr:
            lines.append(line)
            if "started on" in line:
                started.set()
            if "recovery:" in line and "streaming again" in line:
                recovered.set()
    threading.Thread(target=read_err, daemon=True).start()
    if not started.wait(120):
        raise RuntimeError("the host did not start: " + "".join(lines))
    time.sleep(2.0)
    t_kill = time.monotonic()
    a.send_signal(signal.SIGTERM)
    a.wait(30)
    time.sleep(1.0)  # the sheet is away for a second
    b = _virtual(vargs)
    while not port.exists():
        time.sleep(0.001)
    t_back = time.monotonic()
    recovered.wait(60)
    time.sleep(3.0)  # streaming after the recovery, for complete_after_pct
    h.send_signal(signal.SIGTERM)  # the host stops as on Ctrl-C and prints its summary
    out, _ = h.communicate(timeout=120)
    b.send_signal(signal.SIGTERM)
    b.wait(30)
    doc = json.loads(out)
    s = doc["summary"]
    recs = [i["t"] for i in s["incidents"] if i["kind"] == "recovery"]
    r = read_recording(rec)
    ts, complete = np.asarray(r.data["timestamp"]), np.asarray(r.data["complete"])
    after_back = ts > t_back
    first = ts[after_back & complete]
    out = {"recovered_s": round(recs[-1] - t_back, 3) if recs else None,
           "first_complete_s": round(float(first[0]) - t_back, 3) if first.size else None,
           "recovered_chips": s["recovered_chips"], "reconnects": s["reconnects"], "resyncs": s["resyncs"]}
    before = ts < t_kill
    out["complete_before_pct"] = round(100 * float(complete[before].mean()), 2) if before.any() else None
    if recs:
        after = ts > recs[-1]
        out["complete_after_pct"] = round(100 * float(complete[after].mean()), 2) if after.any() else None
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    configs = [("pty", "6x6", "drive", 50.0), ("pty", "6x6", "follow", 50.0), ("slcan", "4x4", "drive", 30.0),
               ("pty", "14x14", "drive", 50.0)]
    if args.quick:
        configs, args.reps = configs[:1], 1
    results = []
    for transport, lattice, sync, rate in configs:
        runs = [one_run(transport, lattice, sync, rate) for _ in range(args.reps)]
        rec = [r["recovered_s"] for r in runs if r["recovered_s"] is not None]
        results.append({"transport": transport, "lattice": lattice, "sync": sync, "rate_hz": rate,
                        "runs": runs, "recovered_s_median": statistics.median(rec) if rec else None,
                        "recovered_s_max": max(rec) if rec else None, "goal_s": 2.0})
    print(json.dumps({"benchmark": "recovery", "load": os.getloadavg(), "results": results}, indent=1))


if __name__ == "__main__":
    main()
