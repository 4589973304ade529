"""Soak: ``capsheet virtual`` + ``capsheet host --record`` for a long run. Prints JSON.

What a five-minute run does not show: memory that grows by tens of MB an hour, a recording's size
per hour, what happens when the 16-bit SYNC counter wraps (every 65536 SYNCs: 452 s at 145 Hz).

Measured:

* ``rss_mb``: every process of both commands (their children too), sampled every ``--sample-s``
  from /proc/<pid>/status (VmRSS); ``growth_after_warmup_mb`` = last sample minus the first
  sample after ``--warmup`` s (samples up to ``--duration``: the host's shutdown after it is not
  the run; its largest sample is ``rss_mb_max_at_shutdown``), ``max_growth_after_warmup_mb`` the
  largest sample minus it,
  ``anon_growth_after_warmup_mb`` the same of RssAnon (the heaps, without mapped files),
  ``steady_growth_after_warmup_mb`` the median of the last minute less the first minute's after
  the warm-up (not moved by a rise of a few seconds that went back: `_steady_growth`).
  Goal: <= 2 MB.
* ``host_probe`` (``--probe EVERY_S``): the host's `host.memory.MemoryProbe` lines (tracked objects
  by type, containers that grew, glibc heap, the cyclic collector's pauses, the aggregator's late
  frames). The probe walks the heap (~0.1 s, a few MB for a moment): not in the runs of docs/benchmarks.md.
* ``completeness_per_minute``: per minute of the host's clock, complete snapshots of the SYNCs
  the host opened (from the recording's ``/capsheet/sync`` and ``/capsheet/snapshot``). Goal:
  >= 99.9 % every minute. Beside it the SYNC thread's largest gap and its gaps over 30 ms (at 145 Hz
  a SYNC is due every 6.9 ms: a gap is the host process, or its interpreter lock, not running).
* ``counter_wraps``: every wrap of the SYNC counter in the recording, with the counters missing
  or incomplete within 2 s of it (``incidents``; goal 0) and the host's own incidents then.
* ``recording``: the files (split every ``--split-duration`` s, so the set is exercised), bytes
  per hour over the run, and per channel (uncompressed message bytes, and zstd level 9 of each
  channel alone over a minute after the warm-up, scaled to an hour: what each costs in the file,
  roughly).
* ``load_average``: /proc/loadavg at start and end (the machine may be shared).

    python benchmarks/bench_soak.py --duration 960 [--packed] [--lattice 14x14] [--rate 145]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CLI = [sys.executable, "-m", "host.cli"]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")
WRAP_WINDOW_S = 2.0
SYNC_GAP_S = 0.030  #: a SYNC this long after the previous one (4 periods at 145 Hz): the host stalled


def _children(pid: int) -> list[int]:
    """``pid`` and every descendant (from /proc/*/stat)."""
    parent: dict[int, int] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    parent[int(d)] = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += [c for c, pp in parent.items() if pp == p]
    return out


def _rss_mb(pid: int) -> tuple[float, float] | None:
    """(VmRSS, RssAnon) in MB: the anonymous part is the heap's; the rest is mapped files (code
    pages of the libraries, touched as new paths run)."""
    got = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(("VmRSS:", "RssAnon:")):
                    got[line.split(":")[0]] = int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return (got["VmRSS"], got.get("RssAnon", got["VmRSS"])) if "VmRSS" in got else None


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return "?"


def _loadavg() -> list[float]:
    with open("/proc/loadavg") as f:
        return [float(v) for v in f.read().split()[:3]]


class _Stalls:
    """Per minute of the host's clock, where late frames come from (``--stalls``): each frame's
    SYNC -> read time (``t_rx`` of its raw chunk minus its counter's SYNC), the receive thread's
    gaps between reads, and the frames over `LATE_S` split by whether a read gap over `LATE_S`
    ended after their SYNC (the host was not reading for part of their wait: it reads the backlog
    then) or not (the host was reading all along: the frame was sent late — the virtual sheet, on
    the same machine)."""

    LATE_S = 0.030

    def __init__(self) -> None:
        import numpy as np

        from host.record.schema import message_class
        from protocol.framing import StreamDecoder
        self.np, self.Raw, self.Frames = np, message_class("RawSerial"), message_class("RawSerialFrames")
        self.expanders: dict = {}  # (file, channel) -> SerialExpander: the compact channel, file by file
        self.dec = StreamDecoder(batch_samples=True)
        self.sync_t = np.full(65536, np.nan)
        self.last_rx = None
        self.gap_end = -np.inf  # t_rx of the read that ended the last read gap over LATE_S
        self.minutes: dict[int, list] = {}

    def sync(self, counter: int, t: float) -> None:
        self.sync_t[counter] = t

    def raw(self, data: bytes, t0: float, compact_key=None) -> None:
        """One raw message; ``compact_key`` (file, channel) for a ``RawSerialFrames`` channel."""
        np = self.np
        if compact_key is None:
            r = self.Raw.FromString(data)
            payload = r.data
        else:
            from host.record.compact import SerialExpander
            r = self.Frames.FromString(data)
            payload = self.expanders.setdefault(compact_key, SerialExpander()).expand(r)
        gap = 0.0 if self.last_rx is None else r.t_rx - self.last_rx
        self.last_rx = r.t_rx
        m = self.minutes.setdefault(int((r.t_rx - t0) // 60), [0.0, 0, 0, 0, 0])
        m[0] = max(m[0], gap)
        m[1] += gap > self.LATE_S
        if gap > self.LATE_S:
            self.gap_end = r.t_rx
        for ev in self.dec.feed(payload):
            c = getattr(ev, "counter", None)
            if c is None or np.isscalar(c):
                continue
            ts = self.sync_t[np.asarray(c, dtype=np.int64)]
            ts = ts[np.isfinite(ts)]
            late = (r.t_rx - ts) > self.LATE_S
            stalled = late & (ts <= self.gap_end)
            m[2] += ts.size
            m[3] += int(np.count_nonzero(stalled))
            m[4] += int(np.count_nonzero(late & ~stalled))

    def per_minute(self) -> list[dict]:
        return [{"minute": k, "read_gap_max_ms": round(1e3 * v[0], 1), "read_gaps_over_30ms": v[1], "frames": v[2],
                 "frames_over_30ms_host_not_reading": v[3], "frames_over_30ms_read_on_time": v[4]}
                for k, v in sorted(self.minutes.items()) if k >= 0]


def _analyse(files: list[Path], duration_s: float, window: tuple[float, float], stalls: bool = False) -> dict:
    """Completeness per minute, counter wraps and channel sizes, streaming through the files."""
    import zstandard
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    from host.record.schema import message_class

    Snapshot, Sync = message_class("Snapshot"), message_class("Sync")
    sizes: dict[str, int] = {}
    comp: dict[str, tuple] = {}
    syncs: list[tuple[int, float]] = []
    snaps: list[tuple[int, float, bool]] = []
    t_first = None
    st = _Stalls() if stalls else None
    for path in files:
        topic: dict[int, str] = {}
        schema: dict[int, str] = {}
        compact: set[int] = set()  # channels of RawSerialFrames
        with open(path, "rb") as f:
            for rec in StreamReader(f).records:
                if isinstance(rec, Schema):
                    schema[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    topic[rec.id] = rec.topic
                    if schema.get(rec.schema_id) == "capsheet.v2.RawSerialFrames":
                        compact.add(rec.id)
                elif isinstance(rec, Message):
                    t = topic[rec.channel_id]
                    data = bytes(rec.data)
                    sizes[t] = sizes.get(t, 0) + len(data)
                    t_first = rec.log_time if t_first is None else t_first
                    if window[0] <= (rec.log_time - t_first) / 1e9 < window[1]:
                        if t not in comp:
                            comp[t] = (zstandard.ZstdCompressor(level=9).compressobj(), [0])
                        c, n = comp[t]
                        n[0] += len(c.compress(data))
                    if t == "/capsheet/sync":
                        m = Sync.FromString(data)
                        syncs.append((m.counter, m.t))
                        if st is not None:
                            st.sync(m.counter, m.t)
                    elif st is not None and t.startswith("/capsheet/raw/") and syncs:
                        st.raw(data, syncs[0][1], (str(path), rec.channel_id) if rec.channel_id in compact else None)
                    elif t == "/capsheet/snapshot":
                        m = Snapshot.FromString(data)
                        snaps.append((m.counter, m.timestamp, m.complete))
    zsize = {t: n[0] + len(c.flush()) for t, (c, n) in comp.items()}
    per_h, per_h_window = 3600.0 / duration_s, 3600.0 / (window[1] - window[0])
    channels = {t: {"messages_bytes_per_h": round(sizes[t] * per_h),
                    "zstd9_bytes_per_h": round(zsize[t] * per_h_window) if t in zsize else None}
                for t in sorted(sizes)}
    # per minute of the host's clock: SYNCs opened, complete snapshots of them
    t0 = syncs[0][1] if syncs else 0.0
    complete_of: dict[tuple[int, float], bool] = {(c, t): ok for c, t, ok in snaps}
    minutes: dict[int, list[int]] = {}
    prev_t = None
    for c, t in syncs:
        m = minutes.setdefault(int((t - t0) // 60), [0, 0, 0.0, 0])
        m[0] += 1
        m[1] += bool(complete_of.get((c, t), False))
        if prev_t is not None:  # the SYNC thread's gaps: the host process (or its lock) not running
            m[2] = max(m[2], t - prev_t)
            m[3] += (t - prev_t) > SYNC_GAP_S
        prev_t = t
    per_minute = [{"minute": k, "syncs": v[0], "complete": v[1],
                   "completeness_pct": round(100.0 * v[1] / v[0], 3) if v[0] else None,
                   "sync_gap_max_ms": round(1e3 * v[2], 1), "sync_gaps_over_30ms": v[3]}
                  for k, v in sorted(minutes.items())]
    wraps = []
    for i in range(1, len(syncs)):
        if syncs[i][0] < syncs[i - 1][0]:  # the counter went round
            tw = syncs[i][1]
            near = [(c, t) for c, t in syncs if abs(t - tw) <= WRAP_WINDOW_S]
            missing = [c for c, t in near if (c, t) not in complete_of]
            incomplete = [c for c, t in near if (c, t) in complete_of and not complete_of[(c, t)]]
            steps = [(syncs[j][0] - syncs[j - 1][0]) % 65536 for j in range(max(1, i - 300), min(len(syncs), i + 300))]
            wraps.append({"t_s": round(tw - t0, 3), "from": syncs[i - 1][0], "to": syncs[i][0],
                          "syncs_within_2s": len(near), "missing": len(missing), "incomplete": len(incomplete),
                          "counter_steps_not_1": sum(s != 1 for s in steps),
                          "incidents": len(missing) + len(incomplete)})
    return {"syncs": len(syncs), "snapshots": len(snaps), "complete": sum(ok for _, _, ok in snaps),
            "completeness_pct": round(100.0 * sum(ok for _, _, ok in snaps) / max(1, len(syncs)), 3),
            "completeness_per_minute": per_minute, "counter_wraps": wraps, "channels": channels,
            **({"late_frames_per_minute": st.per_minute()} if st is not None else {})}


#: `_steady_growth` compares the median resident size of this window at each end of the run (s)
STEADY_WINDOW_S = 60.0


def _steady_growth(series: list, warmup_s: float, end_s: float, window_s: float = STEADY_WINDOW_S) -> float | None:
    """Median RSS over the last ``window_s`` before ``end_s`` less the median over the first
    ``window_s`` after ``warmup_s`` (MB): what stayed. A live host's resident size rises by 5-9 MB
    for a few seconds about every 40 s while it estimates (measured at 0.5 s: gone without
    estimates) and one sample can fall in such a rise — ``growth_after_warmup_mb`` takes single
    samples, ``max_growth_after_warmup_mb`` the highest; this one is not moved by a rise that
    went back."""
    first = [mb for t, mb in series if warmup_s <= t < warmup_s + window_s]
    last = [mb for t, mb in series if end_s - window_s < t <= end_s]
    if not first or not last or end_s - warmup_s < 2 * window_s:
        return None
    return round(float(np.median(last) - np.median(first)), 2)


def run(args) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="bench-soak-"))
    port, lay, rec = tmp / "port", tmp / "sheet.csv", tmp / "run.mcap"
    vargs = ["--lattice", args.lattice, "--symlink", str(port), "--layout-out", str(lay)]
    if args.packed:
        vargs += ["--packed"]
    if args.noise is not None:
        vargs += ["--noise", f"{args.noise:g}"]
    load0 = _loadavg()
    burners = [subprocess.Popen(["nice", "-n", str(args.load_nice), sys.executable, "-c", "while True: pass"])
               for _ in range(args.load)]
    virt = subprocess.Popen(CLI + ["virtual", *vargs], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, env=ENV, cwd=ROOT)
    host = None
    try:
        cmd = None
        for line in virt.stdout:
            if line.strip().startswith("capsheet host "):
                cmd = line.split()[2:]
                break
        if cmd is None:
            raise RuntimeError("capsheet virtual printed no host command")
        threading.Thread(target=lambda: [None for _ in virt.stdout], daemon=True).start()
        if "--rate" in cmd:
            cmd[cmd.index("--rate") + 1] = f"{args.rate:g}"
        else:
            cmd += ["--rate", f"{args.rate:g}"]
        hcmd = ["host", *cmd, "--duration", f"{args.duration:g}", "--json", "-q", "--record", str(rec),
                "--overwrite"]
        if args.split_duration:
            hcmd += ["--split-duration", f"{args.split_duration:g}"]
        hcmd += args.host_arg
        henv = dict(ENV)
        if args.probe:
            henv["CAPSHEET_MEMORY_PROBE"] = f"{tmp / 'probe.jsonl'},{args.probe:g}"
        host = subprocess.Popen(CLI + hcmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=henv,
                                cwd=ROOT)
        err: list[str] = []
        threading.Thread(target=lambda: err.extend(host.stderr), daemon=True).start()
        out: list[str] = []
        threading.Thread(target=lambda: out.append(host.stdout.read()), daemon=True).start()
        t_start = time.monotonic()
        samples = []  # (t, {pid: rss}), recording bytes
        names: dict[int, str] = {}
        while host.poll() is None:
            t = time.monotonic() - t_start
            row = {}
            for who, root in (("host", host.pid), ("virtual", virt.pid)):
                for pid in _children(root):
                    mb = _rss_mb(pid)
                    if mb is not None:
                        row[pid] = mb
                        names.setdefault(pid, f"{who}: {_cmdline(pid)[:90]}")
            size = sum(p.stat().st_size for p in tmp.glob("run*.mcap"))
            samples.append((t, row, size))
            time.sleep(args.sample_s)
        host.wait()
        load1 = _loadavg()
    finally:
        for b in burners:
            b.kill()
            b.wait()
        for p in (host, virt):
            if p is not None and p.poll() is None:
                p.terminate()
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
    procs = {}
    for pid, name in names.items():
        # over the run: from the warm-up to the end of --duration (the host's shutdown after it —
        # the recording's summary written, statistics — is not the run)
        anon = [row[pid][1] for t, row, _ in samples if pid in row and args.warmup <= t <= args.duration]
        series = [(t, row[pid][0]) for t, row, _ in samples if pid in row]
        after = [mb for t, mb in series if args.warmup <= t <= args.duration]
        procs[name] = {"pid": pid, "samples": len(series),
                       "rss_mb_first": round(series[0][1], 1) if series else None,
                       "rss_mb_at_warmup": round(after[0], 1) if after else None,
                       "rss_mb_last": round(series[-1][1], 1) if series else None,
                       "rss_mb_max": round(max(mb for _, mb in series), 1) if series else None,
                       "growth_after_warmup_mb": round(after[-1] - after[0], 2) if after else None,
                       "max_growth_after_warmup_mb": round(max(after) - after[0], 2) if after else None,
                       "anon_growth_after_warmup_mb": round(anon[-1] - anon[0], 2) if anon else None,
                       "steady_growth_after_warmup_mb": _steady_growth(series, args.warmup, args.duration),
                       "rss_mb_max_at_shutdown": round(max((mb for t, mb in series if t > args.duration), default=0.0), 1),
                       "rss_mb_every_minute": [round(mb, 1) for t, mb in series[::max(1, int(60 / args.sample_s))]]}
    files = sorted(tmp.glob("run_*.mcap")) or [rec]
    total = sum(p.stat().st_size for p in files)
    # bytes per hour over the steady part: recording size growth from warm-up end to the last sample
    steady = [(t, s) for t, _, s in samples if t >= args.warmup]
    slope = ((steady[-1][1] - steady[0][1]) / (steady[-1][0] - steady[0][0]) * 3600.0
             if len(steady) > 1 and steady[-1][0] > steady[0][0] else None)
    w0 = min(args.warmup, max(0.0, args.duration - 60.0))
    analysis = _analyse(files, args.duration, (w0, w0 + min(60.0, args.duration)), stalls=args.stalls)
    try:
        summary = json.loads(out[0]) if out and out[0].strip() else None
    except ValueError:
        summary = None
    s = (summary or {}).get("summary", {})
    doc = {
        "config": {"host_args": args.host_arg, "load_processes": args.load, "load_nice": args.load_nice, "lattice": args.lattice, "mode": "packed" if args.packed else "per-chip", "rate_hz": args.rate,
                   "duration_s": args.duration, "warmup_s": args.warmup, "sample_s": args.sample_s,
                   "split_duration_s": args.split_duration, "noise_pct_g": args.noise},
        "machine": {"cpus": os.cpu_count(), "load_average_start": load0, "load_average_end": load1},
        "host_exit": host.returncode,
        "processes": procs,
        "max_growth_after_warmup_mb": max((p["growth_after_warmup_mb"] or 0.0) for p in procs.values()) if procs else None,
        "max_steady_growth_after_warmup_mb": max((p["steady_growth_after_warmup_mb"] or 0.0) for p in procs.values())
        if procs else None,
        "recording": {"files": [p.name for p in files], "bytes": total,
                      "bytes_per_hour": round(total / args.duration * 3600.0),
                      "gb_per_hour": round(total / args.duration * 3600.0 / 1e9, 3),
                      "steady_bytes_per_hour": round(slope) if slope else None,
                      "channels": analysis.pop("channels")},
        **analysis,
        "min_minute_completeness_pct": min((m["completeness_pct"] for m in analysis["completeness_per_minute"]
                                            if m["completeness_pct"] is not None), default=None),
        "host_summary": {k: s.get(k) for k in ("snapshots", "complete_snapshots", "complete_snapshots_pct",
                                                "resyncs", "late", "reconnects", "recoveries", "stray_frames",
                                                "events_cut", "rx_errors")} if s else None,
        "host_aggregator": {k: (summary or {}).get("aggregator", {}).get(k) for k in
                            ("emitted", "complete", "incomplete", "late", "late_raises", "input_holds")},
        "host_incidents": [i for i in s.get("incidents", []) if i.get("kind") not in ("info",)][:50] if s else None,
        "host_stderr_tail": "".join(err[-8:]),
    }
    probe = tmp / "probe.jsonl"
    if probe.exists():
        doc["host_probe"] = [json.loads(line) for line in probe.read_text().splitlines() if line.strip()]
    if not args.keep:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        doc["recording"]["dir"] = str(tmp)
    return doc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=960.0, help="seconds (default 960: two counter wraps)")
    ap.add_argument("--lattice", default="14x14")
    ap.add_argument("--rate", type=float, default=145.0)
    ap.add_argument("--packed", action="store_true", help="the gateway answers SYNC with SNAPSHOT frames")
    ap.add_argument("--noise", type=float, default=None,
                    help="capsheet virtual --noise: sensor noise, %% of g per axis (default: virtual's 0.02)")
    ap.add_argument("--warmup", type=float, default=120.0, help="s before memory growth is counted (default 120)")
    ap.add_argument("--sample-s", type=float, default=5.0)
    ap.add_argument("--split-duration", type=float, default=300.0,
                    help="capsheet host --split-duration (default 300; 0: one file)")
    ap.add_argument("--keep", action="store_true", help="keep the recording (its folder is printed)")
    ap.add_argument("--out", help="also write the JSON here")
    ap.add_argument("--stalls", action="store_true",
                    help="also decode the recorded raw input: per minute, frames read over 30 ms after their SYNC, "
                         "after a gap in the host's reading or not (late_frames_per_minute; ~1 min more per 16)")
    ap.add_argument("--host-arg", action="append", default=[], metavar="ARG",
                    help="one more argument for capsheet host (repeat), e.g. --host-arg=--no-input-hold")
    ap.add_argument("--load", type=int, default=0, metavar="N",
                    help="N busy processes beside the run (a loaded machine, reproducibly), at --load-nice")
    ap.add_argument("--load-nice", type=int, default=10, help="their niceness (default 10)")
    ap.add_argument("--probe", type=float, default=0.0, metavar="EVERY_S",
                    help="the host writes host.memory.MemoryProbe lines every EVERY_S s (types of objects "
                         "that grow, glibc heap, the cyclic collector's pauses): in the JSON as host_probe")
    ap.add_argument("--analyse", metavar="DIR",
                    help="no run: analyse the recording a --keep run left in DIR (completeness, wraps, --stalls)")
    args = ap.parse_args()
    if args.analyse:
        files = sorted(Path(args.analyse).glob("run_*.mcap")) or [Path(args.analyse) / "run.mcap"]
        doc = _analyse(files, args.duration, (args.warmup, args.warmup + 60.0), stalls=args.stalls)
        doc["min_minute_completeness_pct"] = min((m["completeness_pct"] for m in doc["completeness_per_minute"]
                                                  if m["completeness_pct"] is not None), default=None)
        print(json.dumps(doc, indent=1))
        return
    doc = run(args)
    text = json.dumps(doc, indent=1)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
