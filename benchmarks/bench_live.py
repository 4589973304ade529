"""The live path, measured: the virtual sheet in its own process on real ptys (serial gateways, or
SLCAN adapters on ptys, one per classic CAN bus), the host in this process, both on this machine.
For each configuration: the highest SYNC rate at which >= 99 % of the SYNCs sent gave a complete
snapshot, the host sent >= 97 % of the rate's SYNC slots and every chip started (`held`), and at 145 Hz the median SYNC -> estimate latency (the estimator run on the newest
snapshot).

    .venv/bin/python benchmarks/bench_live.py            # full sweep, JSON on stdout (many minutes)
    .venv/bin/python benchmarks/bench_live.py --quick    # a short sweep (a few minutes)
    .venv/bin/python benchmarks/bench_live.py --only 14x14-packed --rates 145,300
    .venv/bin/python benchmarks/bench_live.py --only 64x64-packed-5gw-record   # ~2 min

``64x64-packed-5gw-record`` runs ``capsheet virtual --lattice 64x64 --packed --gateways 5``
and ``capsheet host`` on its five ports as a user does, at 145 Hz with ``--record --live-rate 145``
(every snapshot recorded and due an estimate), once as the host was and once with
``--reader-processes --estimate-process``; per design the share of snapshots complete, estimated
and recorded, the SYNCs sent, and the CPU of every process (% of one core: the virtual sheet, which a
real sheet does not put on this machine, the host's main process, its readers, its estimator, its
recording's writer) with the cost per link sample, and CPU milliseconds per snapshot per process
(``cpu_ms_per_snapshot``: comparable on a loaded machine, where shares of a core are not). ``64x64-packed-5gw-record-gwsync`` is the same with gateway 0 generating
the SYNC (``capsheet virtual --rate 145``) and the host following it (``--sync follow``): its SYNC
rate is the gateway's SYNCs that opened a snapshot, per second of streaming.

Configurations: 14x14 per-chip, 14x14 packed, 32x32 packed over two serial gateways of
12 Mbaud merged into one lattice (1,984 links exceed one 12 Mbaud UART at 145 Hz by the capacity
table) and, for comparison, over one gateway declared as a 24 Mbaud link; 14x14 over as many
classic CAN buses as the capacity table says for 145 Hz (9, SLCAN on ptys); 14x14 with the C
firmware (one cffi chip per link); 14x14 per-chip again with one core kept busy (a
``python3 -c 'while True: pass'`` beside it); 6-axis chips on a carried-and-turned sheet,
per chip over the two 12 Mbaud gateways their IMU_SAMPLEs need at 145 Hz and packed in SNAPSHOT_IMU
over one, each row with that capacity (``capacity_at_145``, `imu_capacity`) and its latency taken
with the fused estimator on every snapshot in order (as ``capsheet demo --sensors`` runs it). A pty has no baud rate: the gateway declares the link
it stands for and the host's capacity check uses that figure (a rate over it counts as not held).

The sweep starts at 145 Hz and walks up the rate grid while rates hold, or down until one holds.
Completeness is counted over one window of SYNC counters (`window_completeness`): numerator and
denominator are the same SYNCs. Figures depend on the machine's load: every row carries
``os.getloadavg()`` and the JSON the load at start and end.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, REPO)

from host.snapshots.snapshot import window_completeness  # noqa: E402
from host.cli import one_blas_thread  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402

CONFIGS = {
    "14x14-per-chip": dict(lattice="14x14", packed=False, transport="serial", baud=12_000_000),
    "14x14-packed": dict(lattice="14x14", packed=True, transport="serial", baud=12_000_000),
    "32x32-packed-2gw": dict(lattice="32x32", packed=True, transport="serial", baud=12_000_000, gateways=2),
    "32x32-packed-24M": dict(lattice="32x32", packed=True, transport="serial", baud=24_000_000),
    "14x14-can": dict(lattice="14x14", packed=False, transport="slcan", bitrate=1_000_000),
    "14x14-firmware-c": dict(lattice="14x14", packed=False, transport="serial", baud=12_000_000, firmware="c"),
    "14x14-per-chip-busy-core": dict(lattice="14x14", packed=False, transport="serial", baud=12_000_000, busy=1),
    # 6-axis chips on a carried-and-turned sheet, shaped by the fused estimator: per chip
    # their IMU_SAMPLEs need two 12 Mbaud gateways at 145 Hz (101 % of one), packed one (58 %)
    "14x14-6axis-per-chip-2gw": dict(lattice="14x14", packed=False, transport="serial", baud=12_000_000,
                                     gateways=2, sensors="accel+gyro"),
    "14x14-6axis-packed": dict(lattice="14x14", packed=True, transport="serial", baud=12_000_000,
                               sensors="accel+gyro"),
}
#: CONFIG_IMU fields per --sensors (format, gyro range code 3 = ±1000 °/s, mag range code 0, flags)
IMU_CONFIG = {"accel+gyro": (1, 3, 0, 0), "accel+gyro+mag": (2, 3, 0, 0)}
#: a 64x64 sheet (8,064 links) on five packed 12 Mbaud gateways at 145 Hz, every snapshot
#: recorded and due an estimate (--record --live-rate 145), run through the CLI as a user runs it
#: (`run_cli_config`): the host as it was ("in-process") and with a reader process per port and the
#: estimates in a process of their own ("processes", docs/host.md); "natural": the command with
#: neither flag, where the host chooses its design for the sheet (`host.cli.host.choose_design`)
CLI_CONFIGS = {
    "64x64-packed-5gw-record": dict(lattice="64x64", gateways=5, rate=145.0, duration=16.0, designs={
        "in-process": ["--no-reader-processes", "--no-estimate-process"],
        "processes": ["--reader-processes", "--estimate-process"],
        "natural": [],
        # the natural command with its recording written in the host's process (``--no-record-process``)
        "natural-record-here": ["--no-record-process"]}),
    # the same with the SYNC generated by gateway 0 (``capsheet virtual --rate 145``, shared with the
    # other four over its SYNC line, docs/protocol.md §13.3) and the host following it: SYNC timing
    # no longer rides on the host's interpreter, which also receives five ports
    "64x64-packed-5gw-record-gwsync": dict(lattice="64x64", gateways=5, rate=145.0, duration=16.0,
                                           virtual_args=["--rate", "145"], designs={
        "processes": ["--reader-processes", "--estimate-process", "--sync", "follow"]}),
}
RATES = [10, 20, 30, 60, 100, 145, 200, 300, 450, 640]
QUICK_RATES = [10, 30, 60, 145, 300, 640]


def sweep_order(rates: list[float], held_at) -> list[float]:
    """The rates to try, adaptively: from 145 Hz (or the grid's nearest) up while each holds, else
    down until one holds. ``held_at(rate) -> bool`` runs one rate. Returns the rates run, in order."""
    grid = sorted(set(rates))
    start = min(grid, key=lambda r: (abs(r - 145.0), r))
    i = grid.index(start)
    done = [start]
    if held_at(start):
        for r in grid[i + 1:]:
            done.append(r)
            if not held_at(r):
                break
    else:
        for r in reversed(grid[:i]):
            done.append(r)
            if held_at(r):
                break
    return done


#: a rate is held only if the host sent at least this share of its SYNC slots (a host that fell
#: behind sent fewer SYNCs, and those few could all complete: 145 Hz read "held" at 68.8 SYNC/s)
MIN_SENT_SHARE = 0.97
#: seconds between two rates with the sheet left alone: a sheet that fell behind still answers the
#: SYNCs it had queued, and the next rate's bring-up would meet that backlog
QUIET_S = 1.0


def held(row: dict, n_links: int) -> bool:
    """The rule a rate must pass: >= 99 % of the window's SYNCs gave a complete snapshot, the host
    sent >= `MIN_SENT_SHARE` of the SYNC slots, and every chip of the layout started (a bring-up
    that found few chips completes its few links easily)."""
    return (row.get("complete_pct", 0.0) >= 99.0
            and row.get("achieved_sync_hz", 0.0) >= MIN_SENT_SHARE * row["rate_hz"]
            and row.get("started", 0) >= n_links)


def _serve(cfg: dict, conn) -> None:
    """Child process: the virtual sheet on its device until told to stop."""
    from virtual_sheet.sheet import VirtualSheet
    kw = {}
    if cfg.get("firmware") == "c":
        from firmware_ref.chip import CFirmwareChip
        kw["chip_factory"] = CFirmwareChip
    can = cfg["transport"] == "slcan"
    sensors = cfg.get("sensors", "accel")
    sheet = VirtualSheet("carry" if sensors != "accel" else "grow", cfg["lattice"], seed=1, noise=1.0,
                         scene_rate_hz=10.0, transport="can" if can else "serial", sensors=sensors, **kw)
    sheet.precompute()
    layout = cfg["layout_path"]
    sheet.write_layout(layout)
    if can:
        from virtual_sheet.slcan import SlcanDevice
        dev = SlcanDevice(sheet, n_buses=cfg["n_buses"])
        paths = dev.paths
    elif cfg.get("gateways", 1) > 1:
        from virtual_sheet.devices import MultiPtyDevice
        dev = MultiPtyDevice(sheet, n_gateways=cfg["gateways"], packed=cfg["packed"])
        paths = dev.paths
    else:
        from virtual_sheet.devices import PtyDevice
        dev = PtyDevice(sheet, packed=cfg["packed"])
        paths = None
    with dev:
        conn.send(("ready", paths or [dev.path]))
        while conn.recv() != "stop":
            pass
    conn.send("stopped")


#: streaming before the window opens: the host's deadline adapts from its first 32 latencies and
#: the estimator's first (cold) solves are slow; `capsheet demo` shows ~1 s of that transient
BRING_UP_LIMIT_S = 180.0  #: a CLI row's host must be streaming by then (a 64x64 bring-up: ~10-20 s)
SETTLE_S = 1.5


def _run_rate(cfg: dict, paths: list[str], rate: float, duration_s: float, estimate_latency: bool) -> dict:
    from host.estimator import estimate
    from host.session.core import Host, Layout
    from host.transport.ports import CanTransport, open_transport

    lat = cfg["lattice"]
    lattice = Lattice.parse(lat)
    rows, cols = lattice.rows, lattice.cols
    if cfg["transport"] == "slcan":
        ts = [CanTransport(f"slcan:{p}", bitrate=cfg["bitrate"], sleep_after_open=0) for p in paths]
    else:
        ts = [open_transport("serial", p, baudrate=cfg["baud"]) for p in paths]
    seen: list[tuple[int, bool]] = []  # (counter, complete) of every snapshot emitted
    host = Host(ts, lat, layout=Layout.load(cfg["layout_path"]), rate_hz=rate,
                on_snapshot=lambda snap: seen.append((snap.counter, snap.complete)))
    fused = None
    if cfg.get("sensors", "accel") != "accel":  # CONFIG_IMU; every snapshot, in order, to the fused estimator
        from host.analysis.motion import MotionEstimator
        from host.analysis.motion.snapshots import fused_update
        host.imu_config = IMU_CONFIG[cfg["sensors"]]
        fused = MotionEstimator(rows, cols, 0.01)
    row: dict = {"rate_hz": rate}
    try:
        with host:
            try:
                up = host.bring_up(packed=cfg["packed"])
            except Exception as exc:  # noqa: BLE001 - e.g. CapacityError: this rate is not held
                row.update(held=False, error=f"{type(exc).__name__}: {exc}")
                return row
            time.sleep(SETTLE_S)  # the deadline adapts and the first estimates run cold: not counted
            agg = host.aggregator
            host.drain()
            first = host.counter  # the next SYNC counter: the window is first .. end - 1
            t_start = time.monotonic()
            lat_ms: list[float] = []
            previous = None
            t_end = time.monotonic() + duration_s
            while time.monotonic() < t_end:
                if estimate_latency and fused is not None:
                    snap = host.get(0.2)
                    if snap is None or not snap.valid.any() or fused_update(fused, snap) is None:
                        continue
                    lat_ms.append(1e3 * (time.monotonic() - snap.timestamp))
                elif estimate_latency:
                    snap = host.latest(0.2)
                    if snap is None or not snap.valid.any():
                        continue
                    previous = estimate(snap.readings, rows, cols, 0.01, valid=snap.valid, previous=previous)
                    lat_ms.append(1e3 * (time.monotonic() - snap.timestamp))
                else:
                    time.sleep(0.05)
                    host.drain()
            end = host.counter
            window_s = time.monotonic() - t_start
            host.stop()  # the counters in flight get their chance to complete
            win = window_completeness(list(seen), first, end)
            row.update(win, achieved_sync_hz=round(win["syncs_sent"] / window_s, 1),
                       syncs_missed=host.stats["live"]["syncs_missed"],
                       deadline_ms=round(1e3 * agg.deadline_s, 1),
                       late=agg.stats.late, started=up["started"], silent_links=len(host.silent_links),
                       valid_links_pct=host.aggregator.completeness()["valid_links_pct"], loadavg=[round(x, 2) for x in os.getloadavg()])
            row["held"] = held(row, rows * (cols - 1) + cols * (rows - 1))
            if fused is not None:
                st = agg.stats
                row["imu_links_pct"] = round(100.0 * st.imu_links / max(1, st.valid_links), 2)  # of valid samples
            if lat_ms:
                row["median_sync_to_estimate_ms"] = round(float(sorted(lat_ms)[len(lat_ms) // 2]), 2)
                row["estimates"] = len(lat_ms)
    finally:
        for t in ts:
            t.close()
    return row


def imu_capacity(cfg: dict) -> dict:
    """What the configuration's IMU records need at 145 Hz, by `capsheet protocol capacity`'s
    functions (`protocol.capacity.bus_load`): each gateway's load and the fewest 12 Mbaud gateways
    that carry the sheet (the links split in near-equal blocks)."""
    from protocol.capacity import bus_load
    n = Lattice.parse(cfg["lattice"]).n_links
    fmt = IMU_CONFIG[cfg["sensors"]][0]
    g = cfg.get("gateways", 1)

    def load(k: int) -> float:
        return bus_load(-(-n // k), 145.0, kind="serial", bitrate=cfg["baud"], packed=cfg["packed"], fmt=fmt)
    return {"framing": "SNAPSHOT_IMU" if cfg["packed"] else "IMU_SAMPLE per chip", "format": fmt,
            "load_pct_per_gateway": round(100 * load(g), 1), "gateways": g,
            "gateways_needed": next(k for k in range(1, 65) if load(k) <= 1.0)}


def run_config(name: str, cfg: dict, rates: list[float], duration_s: float, tmp: str, fixed: bool = False) -> dict:
    """One configuration: the sheet in a child process, the host here, the rates swept
    (`sweep_order`; ``fixed``: exactly ``rates``, in order)."""
    cfg = dict(cfg, layout_path=os.path.join(tmp, f"{name}.json"))
    if cfg["transport"] == "slcan":
        from protocol.capacity import buses_needed
        n_links = Lattice.parse(cfg["lattice"]).n_links
        cfg["n_buses"] = next(k for c, k in buses_needed(n_links, 145.0) if "classic" in c.link)
    if cfg.get("firmware") == "c":
        try:
            import firmware_ref.chip  # noqa: F401
        except ImportError as exc:
            return {"config": name, "skipped": f"C firmware not built: {exc}"}
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cfg.get("busy", 0))]
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_serve, args=(cfg, child), daemon=True)
    proc.start()
    out: dict = {"config": name, **{k: v for k, v in cfg.items() if k != "layout_path"}, "sweep": []}
    if cfg.get("sensors", "accel") != "accel":
        out["capacity_at_145"] = imu_capacity(cfg)
    try:
        if not parent.poll(180):
            raise RuntimeError("virtual sheet did not start")
        _, paths = parent.recv()

        def held_at(r: float) -> bool:
            if out["sweep"]:
                time.sleep(QUIET_S)
            row = _run_rate(cfg, paths, float(r), duration_s, estimate_latency=(r == 145))
            out["sweep"].append(row)
            print(json.dumps({"config": name, **row}), file=sys.stderr, flush=True)
            return bool(row.get("held"))
        if fixed:
            for r in rates:
                held_at(r)
        else:
            sweep_order(rates, held_at)
        held = [row["rate_hz"] for row in out["sweep"] if row.get("held")]
        out["highest_rate_99pct_hz"] = max(held) if held else None
        at145 = [row for row in out["sweep"] if row["rate_hz"] == 145]
        out["median_sync_to_estimate_ms_at_145"] = at145[0].get("median_sync_to_estimate_ms") if at145 else None
    finally:
        if proc.is_alive():
            parent.send("stop")
            proc.join(15)
            if proc.is_alive():
                proc.terminate()
        for b in busy:
            b.kill()
            b.wait()
    return out


def _proc_tree(root: int) -> list[int]:
    kids: dict[int, list[int]] = {}
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                stat = open(f"/proc/{p}/stat").read()
            except OSError:
                continue
            kids.setdefault(int(stat.rsplit(")", 1)[1].split()[1]), []).append(int(p))
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += kids.get(p, [])
    return out


def _cpu_ticks(root: int, system: bool = False) -> dict[int, tuple[str, int]]:
    """pid -> (what it is, utime + stime ticks) for ``root`` and its descendants (``system``: stime
    alone, the kernel's work for it: pty and pipe copies, wake-ups)."""
    out = {}
    for p in _proc_tree(root):
        try:
            stat = open(f"/proc/{p}/stat").read()
            cmd = open(f"/proc/{p}/cmdline", "rb").read().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        f = stat.rsplit(")", 1)[1].split()
        what = ("reader" if " -S -c " in cmd else "estimator" if "spawn_main" in cmd
                else "recorder" if "host.record.writer_process" in cmd
                else "mp-resource-tracker" if "resource_tracker" in cmd else "main")
        out[p] = (what, int(f[12]) if system else int(f[11]) + int(f[12]))
    return out


def _cpu_pct(a: dict, b: dict, dt: float) -> dict[str, float]:
    """% of one core per kind of process between two `_cpu_ticks`."""
    hz = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for p, (what, t) in b.items():
        if p in a:
            out[what] = out.get(what, 0.0) + 100.0 * (t - a[p][1]) / hz / dt
    return {k: round(v, 1) for k, v in sorted(out.items())}


def _recorded_rate(path: str) -> float:
    """Snapshots per second of a recording, over its snapshots' span (their host times)."""
    from host.record.recording import iter_snapshots
    first = last = None
    n = 0
    for b in iter_snapshots(path, batch=1024):
        if first is None:
            first = float(b.timestamp[0])
        last = float(b.timestamp[-1])
        n += len(b)
    return round((n - 1) / (last - first), 1) if n > 1 and last > first else 0.0


#: seconds of a CLI row's streaming over which the CPU of each process is sampled (a --duration
#: longer than the default 16 s: all but its first 10 s, for longer profiles)
CPU_WINDOW_S = 6.0
PY_SPY = os.environ.get("PY_SPY", "/work/tools/spyvenv/bin/py-spy")


def _spy(outdir: str, base: str, pids: dict[str, int], seconds: float) -> list:
    """``py-spy record`` of each process (raw folded stacks, samples of the thread holding the
    interpreter lock: the Python work, and C calls that keep the lock) for ``seconds``:
    ``<outdir>/<row>-<what>.txt``. Started beside the CPU window, so that window's figures carry
    py-spy's own cost (a profiled run is for the profile, not for the figures)."""
    os.makedirs(outdir, exist_ok=True)
    return [subprocess.Popen([PY_SPY, "record", "--nonblocking", "--gil", "-r", "100", "-d", f"{seconds:g}", "-f", "raw",
                              "-o", os.path.join(outdir, f"{os.path.basename(base)}-{what}.txt"), "-p", str(pid)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for what, pid in pids.items()]


def _recorded_between(path: str, t0: float, t1: float) -> int:
    """Snapshots of a recording whose SYNC (host monotonic ``timestamp``) fell in [t0, t1)."""
    from host.record.recording import iter_snapshots
    n = 0
    for b in iter_snapshots(path, batch=1024):
        ts = b.timestamp
        n += int(((ts >= t0) & (ts < t1)).sum())
    return n


def _cpu_ms_per(*spans: dict, snapshots: int) -> dict[str, float]:
    """CPU milliseconds per snapshot, per kind of process, from pairs of `_cpu_ticks` (a prefix per
    pair, e.g. ``{"host": (a, b)}``: ``host_main``, ``host_reader`` (all readers together), ...);
    ``total``: all of them but the resource tracker."""
    hz = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for span in spans:
        for prefix, (a, b) in span.items():
            for p, (what, t) in b.items():
                if p in a and what != "mp-resource-tracker":
                    key = prefix if prefix == "virtual_sheet" else f"{prefix}_{what}"
                    out[key] = out.get(key, 0.0) + 1e3 * (t - a[p][1]) / hz / max(1, snapshots)
    out["total"] = sum(out.values())
    return out


def run_cli_config(name: str, cfg: dict, tmp: str, designs: list[str] | None = None,
                   profile: str | None = None) -> dict:
    """``capsheet virtual`` and ``capsheet host`` as a user runs them (subprocesses, the host's
    ``--json`` summary), per design: completeness, the share of snapshots estimated and recorded,
    the SYNCs sent, and the CPU of every process (% of one core, sampled over the streaming
    window from /proc: the virtual sheet apart, the host's main process, its readers and its
    estimator), with the load average beside."""
    cli = [sys.executable, "-m", "host.cli"]
    lat, gw, rate = cfg["lattice"], cfg["gateways"], cfg["rate"]
    n_links = Lattice.parse(lat).n_links
    out: dict = {"config": name, "lattice": lat, "gateways": gw, "rate_hz": rate, "duration_s": cfg["duration"],
                 "rows": []}
    for design, extra in cfg["designs"].items():
        if designs and design not in designs:
            continue
        base = os.path.join(tmp, f"{name}-{design}")
        lay, rec = base + ".json", base + ".mcap"
        vlog = open(base + "-virtual.log", "w+")
        virt = subprocess.Popen(cli + ["virtual", "--lattice", lat, "--packed", "--gateways", str(gw), "--symlink",
                                       base + "-gw", "--layout-out", lay, "--overwrite", "--duration", "600",
                                       *cfg.get("virtual_args", [])],
                                stdout=vlog, stderr=subprocess.STDOUT, start_new_session=True, cwd=REPO)
        row: dict = {"design": design, "host_args": extra}
        try:
            t_end = time.monotonic() + 180
            while time.monotonic() < t_end:
                vlog.seek(0)
                if "layout written" in vlog.read():
                    break
                time.sleep(0.3)
            ports = sum((["--port", f"{base}-gw{i}"] for i in range(gw)), [])
            cmd = cli + ["host", *ports, "--baud", "12000000", "--layout", lay, "--rate", f"{rate:g}",
                         "--duration", f"{cfg['duration']:g}", "--record", rec, "--overwrite", "--live-rate",
                         f"{rate:g}", "--allow-missing", "--json", "-q", *extra]
            row["command"] = " ".join(["capsheet", *cmd[len(cli):]])
            herr = open(base + "-host.err", "w+")
            hp = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=herr, text=True, cwd=REPO)
            started_by = time.monotonic() + BRING_UP_LIMIT_S
            while hp.poll() is None:
                herr.seek(0)
                if "started on" in herr.read():
                    break
                if time.monotonic() > started_by:  # a hung bring-up is a row, not a hung benchmark
                    hp.kill()
                    hp.wait()
                    raise TimeoutError(f"the host did not start streaming within {BRING_UP_LIMIT_S:g} s "
                                       f"(its stderr: {base}-host.err)")
                time.sleep(0.2)
            time.sleep(SETTLE_S + 1.5)
            window = max(CPU_WINDOW_S, cfg["duration"] - 10.0)
            spies = _spy(profile, base, {"main": hp.pid, "virtual": virt.pid}, window) if profile else []
            a_v, a_h, t0 = _cpu_ticks(virt.pid), _cpu_ticks(hp.pid), time.monotonic()
            sa_v, sa_h = _cpu_ticks(virt.pid, True), _cpu_ticks(hp.pid, True)
            time.sleep(window)
            b_v, b_h, t1 = _cpu_ticks(virt.pid), _cpu_ticks(hp.pid), time.monotonic()
            sb_v, sb_h = _cpu_ticks(virt.pid, True), _cpu_ticks(hp.pid, True)
            for spy in spies:
                spy.wait(30)
            row["loadavg"] = [round(x, 2) for x in os.getloadavg()]
            stdout, _ = hp.communicate(timeout=300)
            doc = json.loads(stdout)
            s = doc["summary"]
            snaps = max(1, s["snapshots"])
            est = s.get("estimates", {})
            host_cpu = _cpu_pct(a_h, b_h, t1 - t0)
            total = sum(v for k, v in host_cpu.items() if k != "mp-resource-tracker")
            in_window = _recorded_between(rec, t0, t1)
            row.update(
                exit=doc["exit"], design_used=doc.get("design"), snapshots=s["snapshots"], syncs_sent=doc["syncs_sent"],
                syncs_seen=doc.get("syncs_seen"), sync_mode=s.get("sync_mode"),
                # SYNCs per second while streaming (sent by the host, or the gateway's when it
                # follows) over the recorded snapshots' own span: a host streams from its
                # bring-up's end, ~0.5-1 s before its --duration starts, so SYNCs or snapshots /
                # --duration read 147-155 Hz for 145 (syncs_seen counts each SYNC once per port,
                # and those heard during the bring-up too)
                sync_rate_hz=_recorded_rate(rec),
                syncs_missed=doc["live"]["syncs_missed"],
                complete_pct=s["complete_snapshots_pct"], valid_links_pct=s["valid_links_pct"],
                estimated_pct=round(100.0 * est.get("made", 0) / snaps, 2), estimates=est,
                recorded_snapshots_pct=round(100.0 * s.get("recorded", {}).get("snapshots", 0) / snaps, 2),
                recorded_estimates=s.get("recorded", {}).get("estimates", 0),
                dropped_from_queue=doc["aggregator"]["dropped"],
                # why a following host's snapshots are incomplete: input after its deadline, a
                # resynced sequence, the SYNC copies of ports read later (`SyncCopies`)
                late_samples=doc["aggregator"]["late"], resyncs=doc["aggregator"]["resyncs"],
                sync_copies=doc.get("sync_copies"),
                cpu_pct={"virtual_sheet": _cpu_pct(a_v, b_v, t1 - t0).get("main", 0.0), **host_cpu},
                host_cpu_pct_total=round(total, 1),
                # CPU seconds per snapshot the host emitted in the same window (the recorded
                # snapshots whose SYNC fell in it), per kind of process: what each costs whatever
                # else the machine runs, unlike a share of a core
                window_snapshots=in_window,
                cpu_ms_per_snapshot={k: round(v, 3) for k, v in _cpu_ms_per(
                    {"virtual_sheet": (a_v, b_v)}, {"host": (a_h, b_h)}, snapshots=in_window).items()},
                cpu_ms_per_snapshot_in_kernel={k: round(v, 3) for k, v in _cpu_ms_per(
                    {"virtual_sheet": (sa_v, sb_v)}, {"host": (sa_h, sb_h)}, snapshots=in_window).items()},
                host_cpu_us_per_link_sample=round(1e6 * total / 100.0 / (n_links * rate), 3))
        except Exception as exc:  # noqa: BLE001 - one design failing is a row, not the end of the run
            row["error"] = f"{type(exc).__name__}: {exc}"
        finally:
            if virt.poll() is None:
                os.killpg(virt.pid, 2)
                try:
                    virt.wait(30)
                except subprocess.TimeoutExpired:
                    os.killpg(virt.pid, 9)
        print(json.dumps({"config": name, **row}), file=sys.stderr, flush=True)
        out["rows"].append(row)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help=f"rate grid {QUICK_RATES}, 2 s each (a few minutes)")
    ap.add_argument("--only", action="append", choices=sorted(CONFIGS) + sorted(CLI_CONFIGS),
                    help="run only this configuration (repeatable); the CLI ones (64x64-packed-5gw-record) run only so")
    ap.add_argument("--design", action="append", help="CLI configurations: only this design (in-process, processes)")
    ap.add_argument("--rates", help="comma-separated SYNC rates, Hz, each run in order (default: the adaptive sweep)")
    ap.add_argument("--duration", type=float, help="seconds streamed per rate (default 5, --quick 2); the CLI "
                    "configurations: the host's --duration (default theirs, 16 s)")
    ap.add_argument("--profile", metavar="DIR", help="CLI configurations: py-spy (PY_SPY, default "
                    f"{PY_SPY}) records the host's main process and the virtual sheet over the CPU window, raw "
                    "folded stacks in DIR (the row's CPU figures then carry py-spy's own cost)")
    args = ap.parse_args(argv)
    one_blas_thread()  # what every capsheet command does: the host's estimates run as the CLI's
    try:
        rates = [float(r) for r in args.rates.split(",")] if args.rates else (QUICK_RATES if args.quick else RATES)
        if any(not r > 0 for r in rates):
            raise ValueError
    except ValueError:
        ap.error(f"invalid --rates {args.rates!r} (need comma-separated rates > 0)")
    duration = args.duration or (2.0 if args.quick else 5.0)
    import tempfile
    tmp = tempfile.mkdtemp(prefix="capsheet-bench-live-")
    load0 = os.getloadavg()
    results = [run_config(n, CONFIGS[n], rates, duration, tmp, fixed=bool(args.rates))
               for n in (args.only or CONFIGS) if n in CONFIGS]
    results += [run_cli_config(n, dict(CLI_CONFIGS[n], **({"duration": args.duration} if args.duration else {})),
                               tmp, args.design, args.profile) for n in (args.only or []) if n in CLI_CONFIGS]
    print(json.dumps({"benchmark": "bench_live", "quick": args.quick, "duration_s": duration, "rates": rates,
                      "loadavg_start": [round(x, 2) for x in load0],
                      "loadavg_end": [round(x, 2) for x in os.getloadavg()], "cpus": os.cpu_count(),
                      "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
