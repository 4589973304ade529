"""A robot of several sheets through Zenoh: N virtual sheets, each with
its ``capsheet host --publish zenoh --no-publish-estimates`` (snapshots only), W estimate workers
(``capsheet estimate --subscribe --worker k/W``) and a recorder subscribing to every sheet's snapshots
and estimates (appending the estimates to a file), all processes on this machine, Zenoh in peer mode
on loopback.

    .venv/bin/python benchmarks/bench_robot.py                     # 8 sheets of 14x14 at 145 Hz, 10 s
    .venv/bin/python benchmarks/bench_robot.py --sheets 2 --lattice 4x4 --duration 3   # a smoke run

Per sheet: snapshots the host made and published, received and estimated by its worker, lost (a
counter skipped on the way, or published and never received), estimates the recorder received, and
the SYNC -> estimate latency (the snapshot's wall time, stamped by the host when its SYNC counter
opened, to the recorder's receipt of its estimate; and to the worker's ``put``) at p50/p99. CPU
seconds of every process (/proc/<pid>/stat, sampled until it exits) per sheet per second of the
run (from the hosts' start to their end; start-up left out: a host's from the end of its bring-up),
by role: host, worker, recorder, and the virtual sheets (the simulated chips, which on a robot
are hardware, so apart). JSON on stdout, with ``os.getloadavg()`` at start and end: the machine is
shared, its load changes the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
CLI = [PY, "-m", "host.cli"]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")
CLK = os.sysconf("SC_CLK_TCK")

RECORDER = r"""
import json, struct, sys, threading, time
import numpy as np, zenoh
sheets, out_path, idle, limit = sys.argv[1].split(","), sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
conf.insert_json5("scouting/multicast/interface", '"lo"')
s = zenoh.open(conf)
HDR = struct.Struct("<4sBBHHIHQdd")
lock = threading.Lock()
st = {n: {"snapshots": 0, "estimates": 0, "estimated": 0, "latency": [], "est_counters": []} for n in sheets}
last = [None]
f = open(out_path, "wb")
def on(sample):
    now = time.time()
    key, data = str(sample.key_expr), sample.payload.to_bytes()
    _, sheet, kind = key.split("/")
    h = HDR.unpack_from(data)
    with lock:
        d = st[sheet]
        last[0] = time.monotonic()
        if kind == "snapshot":
            d["snapshots"] += 1
            return
        d["estimates"] += 1
        d["estimated"] += not h[2] & 2
        d["latency"].append(now - h[-1])
        d["est_counters"].append(h[7])
        f.write(struct.pack("<I", len(data)) + data)
subs = [s.declare_subscriber(f"capsheet/{n}/{k}", on) for n in sheets for k in ("snapshot", "estimate")]
print("ready", flush=True)
t_end = time.monotonic() + limit
while time.monotonic() < t_end:
    with lock:
        if last[0] is not None and time.monotonic() - last[0] > idle:
            break
    time.sleep(0.1)
for x in subs:
    x.undeclare()
s.close()
f.close()
res = {}
for n, d in st.items():
    lat = np.array(d["latency"])
    c = d["est_counters"]
    res[n] = {"snapshots": d["snapshots"], "estimates": d["estimates"], "estimated": d["estimated"],
              "in_order": all((b - a) % 65536 == 1 for a, b in zip(c, c[1:])),
              "latency_p50_ms": round(float(np.percentile(lat, 50)) * 1e3, 2) if lat.size else None,
              "latency_p99_ms": round(float(np.percentile(lat, 99)) * 1e3, 2) if lat.size else None,
              "latencies_s": lat.tolist()}
print(json.dumps(res), flush=True)
"""


def cpu_s(pid: int) -> float | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / CLK  # utime, stime


class Watched:
    """A subprocess whose CPU time is sampled until it exits (the last sample is kept)."""

    def __init__(self, role: str, args: list[str], **kw) -> None:
        self.role = role
        self.p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
                                  cwd=ROOT, **kw)
        self.cpu = 0.0
        self.lines: list[str] = []

    def read_in_threads(self, mark: str | None = None) -> None:
        """Collect stdout and stderr in threads; at the first stderr line holding ``mark``, sample the
        CPU time (`cpu_mark`: a host's bring-up is over, streaming starts)."""
        self.out: list[str] = []
        self.cpu_mark = None

        def err():
            for line in self.p.stderr:
                self.lines.append(line)
                if mark is not None and self.cpu_mark is None and mark in line:
                    self.sample()
                    self.cpu_mark = self.cpu
        self._threads = [threading.Thread(target=lambda: self.out.extend(self.p.stdout), daemon=True),
                         threading.Thread(target=err, daemon=True)]
        for t in self._threads:
            t.start()

    def wait(self, timeout: float) -> tuple[str, str]:
        self.p.wait(timeout)
        for t in self._threads:
            t.join(10)
        return "".join(self.out), "".join(self.lines)

    def sample(self) -> None:
        c = cpu_s(self.p.pid)
        if c is not None:
            self.cpu = c


def names_for(n: int, workers: int) -> list[str]:
    """``n`` sheet names split as evenly as possible among ``workers`` by CRC-32 modulo ``workers``
    (the rule ``--worker`` uses)."""
    want = [n // workers + (k < n % workers) for k in range(workers)]
    got: list[str] = []
    k = 0
    while len(got) < n:
        name = f"robot_{k}"
        w = zlib.crc32(name.encode()) % workers
        if want[w] > 0:
            want[w] -= 1
            got.append(name)
        k += 1
    return got


def pct(values, q):
    import numpy as np
    v = np.asarray(values, dtype=float)
    return round(float(np.percentile(v, q)) * 1e3, 2) if v.size else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sheets", type=int, default=8)
    ap.add_argument("--lattice", default="14x14")
    ap.add_argument("--rate", type=float, default=145.0)
    ap.add_argument("--duration", type=float, default=10.0, help="seconds each host streams")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--per-chip", action="store_true", help="per-chip frames (default: packed, one frame per row)")
    a = ap.parse_args()
    load0 = os.getloadavg()
    names = names_for(a.sheets, a.workers)
    tmp = Path(tempfile.mkdtemp(prefix="bench_robot_"))
    procs: list[Watched] = []
    stop = threading.Event()

    def sampler():
        while not stop.is_set():
            for w in procs:
                if w.p.poll() is None:
                    w.sample()
            time.sleep(0.25)
    threading.Thread(target=sampler, daemon=True).start()
    try:
        virtuals = []
        for k, name in enumerate(names):
            v = Watched("virtual", CLI + ["virtual", "--lattice", a.lattice, "--symlink", str(tmp / f"sheet{k}"),
                                         "--layout-out", str(tmp / f"s{k}.csv")]
                        + ([] if a.per_chip else ["--packed"]))
            procs.append(v)
            virtuals.append(v)
        host_cmds = []
        for v in virtuals:
            for line in v.p.stdout:
                if line.strip().startswith("capsheet host "):
                    host_cmds.append(line.strip().split()[2:])
                    break
        workers = [Watched("worker", CLI + ["estimate", "--subscribe", "--sheets", "robot_*", "--worker", f"{k}/{a.workers}", "--idle", "8",
                                            "--duration", str(a.duration + 300), "--json", "-q"])
                   for k in range(a.workers)]
        procs += workers
        for w in workers:
            for line in w.p.stderr:
                if "worker ready" in line:
                    break
        rec = Watched("recorder", [PY, "-c", RECORDER, ",".join(names), str(tmp / "estimates.bin"), "10",
                                   str(a.duration + 300)])
        procs.append(rec)
        assert rec.p.stdout.readline().strip() == "ready"
        time.sleep(1.0)  # Zenoh's scouting finds the peers
        for w in procs:
            w.sample()
        cpu0 = {id(w): w.cpu for w in procs}  # the start-up (imports, scouting) is not the run's
        t0 = time.monotonic()
        hosts = [Watched("host", CLI + ["host", *cmd, "--rate", str(a.rate), "--duration", str(a.duration),
                                        "--publish", "zenoh", "--no-publish-estimates", "--sheet-name", name,
                                        "--json", "-q"])
                 for cmd, name in zip(host_cmds, names)]
        procs += hosts
        for h in hosts:
            h.read_in_threads(mark=" started on ")
        host_out = [h.wait(timeout=a.duration + 300) for h in hosts]
        t_hosts = time.monotonic() - t0
        for w in procs:
            if w.p.poll() is None:
                w.sample()
        cpu1 = {id(w): w.cpu for w in procs}  # the hosts' last sample: before their exit
        worker_out = [w.p.communicate(timeout=600) for w in workers]
        rec_out = rec.p.communicate(timeout=600)
        for v in virtuals:
            v.sample()
            v.p.terminate()
            v.p.wait(30)
    finally:
        stop.set()
        for w in procs:
            if w.p.poll() is None:
                w.p.kill()
    load1 = os.getloadavg()
    wdocs = {}
    for (out, err) in worker_out:
        d = json.loads(out)
        for s in d["sheets"]:
            wdocs[s["sheet"]] = {**s, "worker_exit": d["exit"], "worker_queue_peak": d["queue_peak"]}
    rdoc = json.loads(rec_out[0].strip().splitlines()[-1])
    rows, all_lat, all_wlat = [], [], []
    for k, name in enumerate(names):
        out, err = host_out[k]
        hd = json.loads(out) if out.strip() else {}
        summ = hd.get("summary") or {}
        published = int(err.split("published ")[1].split(" snapshots")[0]) if "published " in err else None
        w = wdocs.get(name, {})
        r = rdoc[name]
        all_lat += r.pop("latencies_s")
        lost = (published - w.get("received", 0)) + w.get("lost", 0) if published is not None else None
        rows.append({"sheet": name, "host_exit": hosts[k].p.returncode, "host_snapshots": summ.get("snapshots"),
                     "host_complete_pct": summ.get("complete_snapshots_pct"),
                     "host_valid_links_pct": summ.get("valid_links_pct"),
                     "published": published, "worker_received": w.get("received"),
                     "worker_estimated": w.get("estimated"), "worker_not_estimated": w.get("not_estimated"),
                     "worker_not_estimated_reasons": w.get("not_estimated_reasons"),
                     "worker_queue_peak": w.get("worker_queue_peak"),
                     "lost": lost, "worker_gaps": w.get("gaps"),
                     "recorder_snapshots": r["snapshots"], "recorder_estimates": r["estimates"],
                     "recorder_in_order": r["in_order"],
                     "sync_to_recorder_p50_ms": r["latency_p50_ms"], "sync_to_recorder_p99_ms": r["latency_p99_ms"],
                     "sync_to_worker_put_p50_ms": (w.get("latency_ms") or {}).get("p50"),
                     "sync_to_worker_put_p99_ms": (w.get("latency_ms") or {}).get("p99"),
                     "snapshots_per_s": round(summ.get("snapshots", 0) / a.duration, 1)})
    cpu = {}
    for role in ("host", "worker", "recorder", "virtual"):
        # from the hosts' start to their end; a host's from the end of its bring-up ("... started on")
        c = sum(cpu1.get(id(w), w.cpu) - (w.cpu_mark if getattr(w, "cpu_mark", None) is not None
                                           else cpu0.get(id(w), 0.0)) for w in procs if w.role == role)
        cpu[role] = {"cpu_s": round(c, 2), "cpu_s_per_sheet_per_s": round(c / a.sheets / a.duration, 4)}
    doc = {"bench": "robot", "sheets": a.sheets, "lattice": a.lattice, "rate_hz": a.rate, "duration_s": a.duration,
           "workers": a.workers, "packed": not a.per_chip, "cores": os.cpu_count(),
           "loadavg_start": load0, "loadavg_end": load1, "hosts_wall_s": round(t_hosts, 2),
           "total": {"published": sum(r["published"] or 0 for r in rows),
                     "estimated_by_workers": sum(r["worker_estimated"] or 0 for r in rows),
                     "lost": sum(r["lost"] or 0 for r in rows),
                     "recorder_estimates": sum(r["recorder_estimates"] for r in rows),
                     "sync_to_recorder_p50_ms": pct(all_lat, 50), "sync_to_recorder_p99_ms": pct(all_lat, 99)},
           "cpu": cpu,
           "cost_per_sheet_cpu_s_per_s": round(sum(cpu[r]["cpu_s_per_sheet_per_s"] for r in ("host", "worker")), 4),
           "per_sheet": rows}
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
