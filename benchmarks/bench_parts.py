"""The cost of reading a real part through its driver in the loop (``--firmware c --part icm42688p``):
every C chip's accelerometer and gyroscope read by the C ICM-42688-P driver over an emulated SPI bus
(firmware_ref/part_chip.py), against the same C chips fed finished counts (``--firmware c``).

Two figures per lattice (6x6, 14x14; 9-axis chips, ``icm42688p+mmc5983ma``, CONFIG_IMU format 2, by
default; ``--sensors accel+gyro`` for 6-axis ``icm42688p``):

* ``cpu_ms_per_sync``: CPU time of this process per SYNC (gateway + every chip + frames), simulated
  time, the best of ``--rounds`` rounds (``time.process_time``), for both engines, and their ratio;
* ``live_part`` / ``live_counts``: ``capsheet virtual --transport pty ... --firmware c [--part icm42688p]``
  and ``capsheet host --rate 100`` in two processes for ``--seconds`` s: the host's complete-snapshot
  percentage (the target: >= 99 % at 6x6 and 100 Hz), with and without the part, side by side
  (what the machine's load takes is in both). A rate the machine cannot hold shows as a lower percentage.

    .venv/bin/python benchmarks/bench_parts.py            # JSON on stdout
    .venv/bin/python benchmarks/bench_parts.py --quick    # fewer SYNCs, shorter live runs
    .venv/bin/python benchmarks/bench_parts.py --per-chip # chip-samples per CPU second, 6- and 9-axis

``--per-chip`` (4x4 by default, ``--lattices``): what one part chip costs, in one process on a
simulated clock at 100 SYNC/s, for the 6-axis (``icm42688p``) and the 9-axis (``icm42688p+mmc5983ma``)
part, two ways: ``sheet_chip_samples_per_cpu_s`` (the whole sheet: gateway, C chips, their parts,
frames; records per CPU second) and ``stack_chip_samples_per_cpu_s`` (the part stack alone: every
link's `LinkSensors.run_to_us` and the C glue's read_axes / read_imu as the chip's HAL calls them,
over the emulated SPI bus, without the chip and the gateway). ``--root DIR`` measures the code of
another checkout (a before figure; it uses DIR's built firmware_ref).

``--process-cpu`` (4x4 9-axis by default): the share of a core the ``capsheet virtual --transport pty
--firmware c --part ...`` process takes while ``capsheet host --rate 50`` streams from it, from its
/proc/PID/stat utime + stime over ``--seconds`` s (5 by default) in the middle of the host's run;
``--no-part``: the same sheet's C chips fed finished counts (what the sheet costs without its parts).

The load average is printed beside the figures (a 2-core machine shared with other work).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
if "--root" in sys.argv[:-1]:   # before the imports: measure another checkout's code
    ROOT = os.path.abspath(sys.argv[sys.argv.index("--root") + 1])
    if not os.path.isfile(os.path.join(ROOT, "firmware_ref", "part_chip.py")):
        print(f"bench_parts: --root {ROOT}: not a capsheet checkout (no firmware_ref/part_chip.py)", file=sys.stderr)
        sys.exit(2)
sys.path.insert(0, ROOT)

from protocol.framing import encode  # noqa: E402
from protocol.messages import ConfigImu, Start, Sync  # noqa: E402
from virtual_sheet.gateway import Gateway  # noqa: E402
from virtual_sheet.sheet import VirtualSheet  # noqa: E402

RATE_HZ = 100.0


def part_for(sensors: str) -> str:
    return "icm42688p+mmc5983ma" if sensors.endswith("mag") else "icm42688p"


def rig(lattice: str, engine: str, sensors: str, *, factory_out: list | None = None):
    from firmware_ref.chip import CFirmwareChip
    from host.cli.virtual import part_chip_factory
    factory = part_chip_factory(part_for(sensors)) if engine == "part" else CFirmwareChip
    if factory_out is not None:
        factory_out.append(factory)
    sheet = VirtualSheet("gaussian", lattice, seed=1, chip_factory=factory, sensors=sensors)
    if engine == "part":
        factory.bind(sheet)
    gw = Gateway(sheet, packed=False)
    gw.power_on(0.0)
    gw.commission(0.1, start=False)
    gw.feed(encode(ConfigImu(0, format=2 if sensors.endswith("mag") else 1, gyro_range=3)), 0.2)
    gw.feed(encode(Start(0)), 0.3)
    t = 0.3
    while t < 2.0:  # bring-up and self-test on the link MCUs' main loops
        gw.poll(t)
        t += 0.01
    gw.pop_output(2.0)
    return gw


def cpu_per_sync(gw, t0: float, counter: int, n: int) -> float:
    frames = [encode(Sync(counter=(counter + i) & 0xFFFF)) for i in range(n)]
    t = t0
    c0 = time.process_time()
    for f in frames:
        t += 1 / RATE_HZ
        gw.feed(f, t)
        gw.poll(t)
        gw.pop_wire(t)
    return (time.process_time() - c0) / n


def stack_per_sync(factory, t0: float, n: int, want_mag: bool) -> float:
    """CPU s per SYNC of the part stacks alone: each link run to the SYNC's instant, then the C glue's
    read_axes and read_imu (what `firmware_ref.part_chip`'s HAL functions call for the chip)."""
    from firmware_ref._ffi import ffi, lib
    xyz, status, out = ffi.new("int16_t[3]"), ffi.new("uint8_t *"), ffi.new("capsheet_imu_reading_t *")
    links = factory.links
    t = t0
    c0 = time.process_time()
    for _ in range(n):
        t += 1 / RATE_HZ
        us = int(round(t * 1e6))
        for ls in links:
            mcu = ls.run_to_us(us)
            lib.capsheet_link_read_axes(ls.ls, mcu, xyz, status)
            lib.capsheet_link_read_imu(ls.ls, mcu, 3, 0, want_mag, out)
    return (time.process_time() - c0) / n


def per_chip(lattice: str, sensors: str, n: int, rounds: int) -> dict:
    fac: list = []
    gw = rig(lattice, "part", sensors, factory_out=fac)
    chips = len(fac[0].links)
    best, t, counter = float("inf"), 2.0, 0
    for _ in range(rounds):
        best = min(best, cpu_per_sync(gw, t, counter, n))
        t += n / RATE_HZ
        counter += n
    stack = min(stack_per_sync(fac[0], t + k * n / RATE_HZ, n, sensors.endswith("mag")) for k in range(rounds))
    return {"lattice": lattice, "part": part_for(sensors), "chips": chips,
            "sheet_chip_samples_per_cpu_s": round(chips / best),
            "stack_chip_samples_per_cpu_s": round(chips / stack),
            "sheet_us_per_chip_sample": round(best / chips * 1e6, 2),
            "stack_us_per_chip_sample": round(stack / chips * 1e6, 2)}


def _cpu_ticks(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])   # utime, stime (fields 14 and 15 of proc(5))


def process_cpu(lattice: str, sensors: str, rate_hz: int, seconds: float, *, part: bool = True) -> dict:
    """The virtual part sheet's % of a core while a host streams from it at ``rate_hz`` SYNC/s
    (``part=False``: the same C chips fed finished counts, the sheet's cost without the parts)."""
    py = sys.executable
    part_args = ["--part", part_for(sensors)] if part else []
    with tempfile.TemporaryDirectory() as tmp:
        link, lay = os.path.join(tmp, "sheet"), os.path.join(tmp, "sheet.csv")
        v = subprocess.Popen([py, "-m", "host.cli", "virtual", "--transport", "pty", "--lattice", lattice,
                              "--sensors", sensors, "--firmware", "c", *part_args,
                              "--symlink", link, "--layout-out", lay], cwd=ROOT, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
        h = None
        try:
            end = time.monotonic() + 120
            while not (os.path.islink(link) and os.path.exists(lay)) and time.monotonic() < end:
                time.sleep(0.1)
            run_s = seconds + 7.0
            h = subprocess.Popen([py, "-m", "host.cli", "host", "--port", link, "--lattice", lattice, "--layout", lay,
                                  "--sensors", sensors, "--rate", str(rate_hz), "--duration", str(run_s),
                                  "--deadline-ms", "2000", "--discover-s", "5", "--min-complete", "0", "-q"],
                                 cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(4.0)   # the host found the chips and streams
            t0, c0 = time.monotonic(), _cpu_ticks(v.pid)
            time.sleep(seconds)
            t1, c1 = time.monotonic(), _cpu_ticks(v.pid)
            h.wait(run_s + 60)
        finally:
            for proc in (h, v):
                _stop(proc)
    share = (c1 - c0) / os.sysconf("SC_CLK_TCK") / (t1 - t0)
    return {"lattice": lattice, "part": part_for(sensors) if part else None, "rate_hz": rate_hz, "seconds": round(t1 - t0, 2),
            "sheet_cpu_pct_of_core": round(100 * share, 1), "host_rc": h.returncode if h is not None else None}


def _stop(proc) -> None:
    """End a process this benchmark started: SIGTERM, then SIGKILL after 30 s."""
    if proc is not None and proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def live(lattice: str, seconds: float, engine: str, sensors: str) -> dict:
    py = sys.executable
    part = ["--part", part_for(sensors)] if engine == "part" else []
    with tempfile.TemporaryDirectory() as tmp:
        link, lay = os.path.join(tmp, "sheet"), os.path.join(tmp, "sheet.csv")
        v = subprocess.Popen([py, "-m", "host.cli", "virtual", "--transport", "pty", "--lattice", lattice,
                              "--sensors", sensors, "--firmware", "c", *part,
                              "--symlink", link, "--layout-out", lay], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        try:
            end = time.monotonic() + 120
            while not (os.path.islink(link) and os.path.exists(lay)) and time.monotonic() < end:
                time.sleep(0.1)
            h = subprocess.run([py, "-m", "host.cli", "host", "--port", link, "--baud", "12000000", "--lattice",
                                lattice, "--layout", lay, "--sensors", sensors, "--rate", str(int(RATE_HZ)),
                                "--duration", str(seconds), "--min-complete", "0", "--json", "-q"], cwd=ROOT, capture_output=True,
                               text=True, timeout=seconds + 240)
        finally:
            _stop(v)
    if h.returncode != 0 or "{" not in h.stdout:
        return {"error": (h.stderr.strip().splitlines() or ["no output"])[-1], "rc": h.returncode}
    s = json.loads(h.stdout[h.stdout.index("{"):])["summary"]
    return {k: s[k] for k in ("snapshots", "complete_snapshots_pct", "valid_links_pct", "imu_links_pct")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer SYNCs, shorter live runs")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=None, help="live run length (default 10, --quick 4); --process-cpu: the window measured (default 5)")
    ap.add_argument("--no-live", action="store_true", help="CPU figures only")
    ap.add_argument("--per-chip", action="store_true",
                    help="chip-samples per CPU second of 6- and 9-axis part chips (module docstring)")
    ap.add_argument("--process-cpu", action="store_true",
                    help="the virtual part sheet process's %% of a core at 50 SYNC/s (module docstring)")
    ap.add_argument("--no-part", action="store_true",
                    help="--process-cpu of the same sheet without the parts (C chips fed finished counts)")
    ap.add_argument("--root", metavar="DIR", help="measure the code of the checkout DIR (a before figure)")
    ap.add_argument("--lattices", default=None,
                    help="comma-separated lattices (default 6x6,14x14; --per-chip: 4x4)")
    ap.add_argument("--sensors", default="accel+gyro+mag", choices=("accel+gyro", "accel+gyro+mag"),
                    help="6-axis (icm42688p) or 9-axis (icm42688p+mmc5983ma) chips (default 9-axis)")
    a = ap.parse_args()
    n = 30 if a.quick else 100
    if a.process_cpu:
        rows = [process_cpu(lattice, a.sensors, 50, a.seconds or 5.0, part=not a.no_part) for lattice in (a.lattices or "4x4").split(",")]
        print(json.dumps({"bench": "parts_process_cpu", "root": os.path.abspath(ROOT), "loadavg": os.getloadavg(),
                          "results": rows}, indent=2))
        return 0
    if a.per_chip:
        rows = [per_chip(lattice, sensors, n, a.rounds) for lattice in (a.lattices or "4x4").split(",")
                for sensors in ("accel+gyro", "accel+gyro+mag")]
        print(json.dumps({"bench": "parts_per_chip", "root": os.path.abspath(ROOT), "syncs": n,
                          "rate_hz": RATE_HZ, "loadavg": os.getloadavg(), "results": rows}, indent=2))
        return 0
    seconds = a.seconds or (4.0 if a.quick else 10.0)
    results = []
    for lattice in (a.lattices or "6x6,14x14").split(","):
        row: dict = {"lattice": lattice, "rate_hz": RATE_HZ}
        for engine in ("counts", "part"):
            t_build = time.perf_counter()
            gw = rig(lattice, engine, a.sensors)
            row[f"bring_up_wall_s_{engine}"] = round(time.perf_counter() - t_build, 2)
            best, t, counter = float("inf"), 2.0, 0
            for _ in range(a.rounds):
                best = min(best, cpu_per_sync(gw, t, counter, n))
                t += n / RATE_HZ
                counter += n
            row[f"cpu_ms_per_sync_{engine}"] = round(best * 1e3, 3)
        row["part_over_counts"] = round(row["cpu_ms_per_sync_part"] / row["cpu_ms_per_sync_counts"], 2)
        row["cpu_share_at_rate"] = round(row["cpu_ms_per_sync_part"] * RATE_HZ / 1e3, 3)
        if not a.no_live:
            for engine in ("counts", "part"):
                row[f"live_{engine}"] = live(lattice, seconds, engine, a.sensors)
        results.append(row)
    print(json.dumps({"bench": "parts", "part": part_for(a.sensors), "sensors": a.sensors, "syncs": n,
                      "loadavg": os.getloadavg(), "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
