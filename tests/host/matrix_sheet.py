"""A virtual sheet for the feature x transport matrix (tests/host/test_matrix.py), run as its own
process: ``python -m tests.host.matrix_sheet [options] [-- capsheet ARGS]``.

It builds a `VirtualSheet` (optionally with realistic chip errors, the calibration board scene, or a
mutant chip of tests/host/conformance/mutants.py) behind the device of ``--transport`` and prints
one line ``PORT <json list of capsheet port arguments>``. Then either

* without ``-- ARGS``: serves until stdin closes (or SIGTERM): a host in another process connects
  (pty, slcan, udp_multicast), or
* with ``-- ARGS``: runs ``capsheet ARGS`` in this very process (``host.cli.main``), with ``{port}``
  in ARGS replaced by the port arguments, and exits with its status: the transports that reach only
  their own process (``memory``: an in-memory link opened as ``memory://NAME``; python-can
  ``virtual``) go through the real command line this way.

``python -m tests.host.matrix_sheet --many SPECS.json`` serves several sheets from one process (a
transport that reaches other processes: pty, slcan, udp_multicast, each sheet on a group of its
own: `udp_group`): SPECS is a list of ``{"name": NAME, "argv":
[options as above]}``; it prints ``PORTS NAME <json list>`` for each, then serves until stdin
closes, stopping a sheet when it reads ``stop NAME`` (its command has ended). Each sheet keeps its
own device, port and thread: the commands see what they saw with a process per sheet, and the
matrix starts one interpreter (and one numpy, one virtual sheet package) where it started six.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys


def port_args(transport: str, dev) -> list[str]:
    if transport == "memory":
        return ["--port", dev.url]
    if transport == "pty":
        return ["--port", dev.path]
    if transport == "slcan":
        return ["--can", f"slcan:{dev.path}", "--bitrate", "1000000"]
    return ["--can", f"{dev.interface}:{dev.channels[0]}"]


def pid_max() -> int:
    with open("/proc/sys/kernel/pid_max") as f:
        return int(f.read())


def udp_group(pid: int, index: int = 0) -> str:
    """A multicast group of this sheet's own, from its process id and its number ``index`` among
    the sheets of its process (``--many``): unique among the processes alive (a process's first
    sheet takes its id, below pid_max; its sheet ``index`` takes ``index`` x pid_max + its id),
    above 239.74.x.x, where the fixed groups the tests use are: sheets isolated to their groups
    (host/transport/udp_multicast.py) run side by side, in one test session or several.
    ValueError when the number does not fit the groups above 239.74 (`fits_udp_groups`)."""
    v = pid + (index * pid_max() if index else 0)
    if 75 + (v >> 16) > 255:
        raise ValueError(f"no multicast group for sheet {index} of process {pid} (pid_max {pid_max()})")
    return f"239.{75 + (v >> 16)}.{(v >> 8) & 255}.{v & 255}"


def fits_udp_groups(n: int) -> bool:
    """Whether a process's ``n`` sheets each get a group of their own (`udp_group`) here."""
    return 75 + ((n * pid_max()) >> 16) <= 255


def build(args, index: int = 0):
    from virtual_sheet.board import DEFAULT_DIRECTIONS, BoardPoseScene
    from virtual_sheet.sensor import chip_error_model
    from virtual_sheet.sheet import VirtualSheet

    can_kind = args.transport in ("slcan", "virtual", "udp_multicast")
    chip_factory = None
    if args.mutant:
        from tests.host.conformance.mutants import MUTANTS
        chip_factory = MUTANTS[args.mutant][0]
    scene = None
    if args.board:
        scene = BoardPoseScene(args.rows, args.cols, 0.01, directions=DEFAULT_DIRECTIONS[:6], hold_s=args.board,
                               move_s=0.3, seed=2)
    sensor = chip_error_model(args.chip_errors, noise_pct_g=args.noise, chip_seed=args.seed)
    sheet = VirtualSheet(args.shape, f"{args.rows}x{args.cols}", scene=scene, sensor=sensor, seed=args.seed,
                         transport="can" if can_kind else "serial", chip_factory=chip_factory, sensors=args.sensors,
                         fd=args.fd and can_kind)
    kw = {"packed": args.packed}
    if args.transport == "memory":
        from virtual_sheet.devices import MemoryDevice
        from virtual_sheet.memport import publish
        dev = MemoryDevice(sheet, **kw)
        dev.url = publish(f"matrix{os.getpid()}", dev.port)
    elif args.transport == "pty":
        from virtual_sheet.devices import PtyDevice
        dev = PtyDevice(sheet, **kw)
    elif args.transport == "slcan":
        from virtual_sheet.slcan import SlcanDevice
        dev = SlcanDevice(sheet, **kw)
    else:
        from virtual_sheet.devices import CanDevice
        channel = (udp_group(os.getpid(), index) if args.transport == "udp_multicast"
                   else f"matrix{os.getpid()}")
        dev = CanDevice(sheet, interface=args.transport, channels=[channel], **kw)
    return sheet, dev


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="matrix_sheet")
    ap.add_argument("--transport", required=True, choices=("memory", "pty", "slcan", "virtual", "udp_multicast"))
    ap.add_argument("--rows", type=int, default=3)
    ap.add_argument("--cols", type=int, default=3)
    ap.add_argument("--shape", default="gaussian")
    ap.add_argument("--noise", type=float, default=0.0, help="%% g")
    ap.add_argument("--chip-errors", default="none", choices=("none", "realistic"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mutant", default=None)
    ap.add_argument("--sensors", default="accel", choices=("accel", "accel+gyro", "accel+gyro+mag"))
    ap.add_argument("--board", type=float, default=0.0, help="the calibration board scene, holding each pose this long (s)")
    ap.add_argument("--packed", action="store_true", help="the gateway packs (SNAPSHOT, or SNAPSHOT_IMU)")
    ap.add_argument("--fd", action="store_true", help="CAN FD chips and bus (CAN transports)")
    ap.add_argument("--layout-out", required=True)
    ap.add_argument("--truth-out", default=None,
                    help="at exit, write the truth of every SYNC counter the sheet answered (npz: counter, "
                         "scene_time_s, joints (n, rows, cols, 3) m), from the sheet's own scene")
    return ap


def serve_many(specs_path: str) -> int:
    """``--many``: every sheet of SPECS in this process (module docstring)."""
    with open(specs_path) as f:
        specs = json.load(f)
    devs = {}
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        for index, spec in enumerate(specs):
            args = parser().parse_args(spec["argv"])
            if args.transport not in ("pty", "slcan", "udp_multicast") or args.truth_out:
                raise SystemExit(f"matrix_sheet --many: {spec['name']}: pty, slcan or udp_multicast sheets, "
                                 "without --truth-out")
            sheet, dev = build(args, index)
            sheet.write_layout(args.layout_out)
            dev.start()
            devs[spec["name"]] = dev
            print(f"PORTS {spec['name']} " + json.dumps(port_args(args.transport, dev)), flush=True)
        for line in sys.stdin:  # until the test closes our stdin
            word, _, name = line.strip().partition(" ")
            if word == "stop" and name in devs:
                devs.pop(name).stop()
        return 0
    finally:
        for dev in devs.values():
            dev.stop()


def main(argv: list[str]) -> int:
    if argv[:1] == ["--many"]:
        return serve_many(argv[1])
    if "--" in argv:
        k = argv.index("--")
        argv, cli = argv[:k], argv[k + 1:]
    else:
        cli = []
    args = parser().parse_args(argv)
    sheet, dev = build(args)
    sheet.write_layout(args.layout_out)
    if args.transport == "memory":
        import serial

        from virtual_sheet.memport import URL_HANDLERS
        serial.protocol_handler_packages.append(URL_HANDLERS)
    dev.start()
    ports = port_args(args.transport, dev)
    print("PORT " + json.dumps(ports), flush=True)
    try:
        if cli:
            from host.cli import main as capsheet
            argv = [a for arg in cli for a in (ports if arg == "{port}" else [arg])]
            return int(capsheet(argv) or 0)
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
        sys.stdin.read()  # until the test closes our stdin
        return 0
    finally:
        dev.stop()
        if args.truth_out:
            write_truth(sheet, args.truth_out)


def write_truth(sheet, path: str) -> None:
    """The joints each answered SYNC counter's readings came from (`VirtualSheet.truth`): what a test
    compares an estimate of the recording with, never computed by the code under test."""
    import numpy as np

    counters = np.array(sorted(sheet.sync_times), dtype=np.uint16)
    times = np.array([sheet.truth_time(int(c)) for c in counters])
    joints = np.stack([sheet.joints_at_scene_time(t) for t in times]) if counters.size else np.zeros((0, 0, 0, 3))
    np.savez(path, counter=counters, scene_time_s=times, joints=joints)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
