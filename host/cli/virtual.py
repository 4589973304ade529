"""``capsheet virtual``: run a virtual sheet behind a pty, SLCAN adapter, python-can bus or
in-memory link, until interrupted."""

from __future__ import annotations

import argparse
import filecmp
import math
import os
import shlex
import signal
import sys
import tempfile
import time

__all__ = ["register", "run", "make_device", "load_chip_factory"]

_EPILOG = """\
transports:
  pty     a serial gateway on a pseudo-terminal; connect: capsheet host --port PATH
          (--gateways N: N gateways, each on its own pty with a contiguous block of the links;
          connect: capsheet host --port PATH0 --port PATH1 ... merges them into one lattice.
          A driving host sends SYNC on every port; with --rate gateway 0 is the SYNC source and
          passes each SYNC to the others over a SYNC line, and every port forwards it)
  slcan   SLCAN (Lawicel) USB-CAN adapter(s) on ptys; connect: capsheet host --can slcan:PATH
  can     python-can buses (--can-interface, default 'virtual': reachable only from this
          process; udp_multicast reaches another process on this machine: connect with
          capsheet host --can udp_multicast:239.74.163.2)
  memory  in-memory link (only useful inside one process; printed for completeness)

fault spec (--faults), comma-separated key=value, e.g.
  bitflip=1e-4,drop_frame=0.01,dead_chip=5,seed=3
  keys: bitflip drop_byte drop_frame dup_frame reorder delay_ms jitter_ms
        dead_chip=L[:L..] dead_after_s babble_chip=L[:L..] babble_rate babble_mode=garbage|flood
        drift_chip=L[:L..] drift drift_late_ms outage_at_s outage_s outage_every_s seed
  (see virtual_sheet/faults.py for the meaning of each)

examples:
  capsheet virtual --shape gaussian --lattice 14x14 --transport pty --layout-out sheet.csv
  capsheet virtual --transport can --can-interface udp_multicast --lattice 6x6 --layout-out sheet.csv
  capsheet virtual --transport slcan --bus-count 2 --fd --packed
  capsheet virtual --lattice 32x32 --packed --gateways 2 --symlink /tmp/sheet --layout-out sheet.json
  capsheet virtual --transport pty --rate 100 --faults bitflip=1e-5,outage_at_s=10,outage_s=2
"""


def part_chip_factory(part: str, **kw):
    """C chips reading ``part`` through its driver (`firmware_ref.part_chip.PartChipFactory`), the
    parts' register emulators and the sheet's truth from the simulator: the command line is where
    the firmware and the simulator meet (docs/design.md §2)."""
    from firmware_ref.part_chip import PartChipFactory
    from virtual_sheet.parts.icm42688p import ICM42688P
    from virtual_sheet.parts.mmc5983ma import MMC5983MA
    from virtual_sheet.parts.truth import SheetTruth
    return PartChipFactory(part, imu_part=ICM42688P, mag_part=MMC5983MA, truth=SheetTruth, **kw)


def load_chip_factory(firmware: str):
    """``python`` -> ChipModel; ``c`` -> firmware_ref.chip.CFirmwareChip (imported lazily)."""
    if firmware == "python":
        from virtual_sheet.chip import ChipModel
        return ChipModel
    if firmware == "c":
        try:
            from firmware_ref.chip import CFirmwareChip
        except Exception as exc:  # ImportError, or the cffi build failing
            raise RuntimeError(f"Cannot import firmware_ref.chip.CFirmwareChip for --firmware c: {exc} "
                               "(is the C firmware built? try `pip install -e .` or use --firmware python)"
                               ) from exc
        return CFirmwareChip
    raise ValueError(f"Unknown firmware {firmware!r} (expected python or c)")


#: the SYNC rate the printed host command drives when the sheet does not lead SYNC (--rate): the
#: paper's, where the link carries it
HOST_RATE_HZ = 145.0


def register(subparsers) -> argparse.ArgumentParser:
    from host.cli import argtypes as T
    from virtual_sheet.shapes import SCENES, SHAPES
    p = subparsers.add_parser(
        "virtual", help="run a virtual sheet on a pty, SLCAN adapter or python-can bus",
        description="Run a simulated capture sheet that a host reaches exactly as hardware: the chips "
                    "announce themselves, take ASSIGN/CONFIG/START and answer SYNC. Prints the port "
                    "(or bus) to connect to, then a summary line per second; Ctrl-C stops.",
        epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    from virtual_sheet.imu_source import MOTION_SHAPES
    p.add_argument("--shape", default="gaussian",
                   help=f"static shape ({', '.join(SHAPES)}), moving scene ({', '.join(SCENES)}) or moving "
                        f"sheet with exact kinematics for 6/9-axis chips ({', '.join(MOTION_SHAPES)}); "
                        "default gaussian")
    p.add_argument("--sensors", choices=("accel", "accel+gyro", "accel+gyro+mag"), default="accel",
                   help="the chips' sensors (docs/protocol.md §16): accel (default), accel+gyro (6-axis) or "
                        "accel+gyro+mag (9-axis); the host asks for the IMU records with CONFIG_IMU")
    p.add_argument("--lattice", type=T.lattice, default="14x14", help="joints ROWSxCOLS (default 14x14)")
    p.add_argument("--link-length", type=T.link_length, default=0.01, help="link length, m (default 0.01)")
    p.add_argument("--transport", choices=("pty", "slcan", "can", "memory"), default="pty",
                   help="how the host reaches the sheet (default pty)")
    p.add_argument("--bus-count", type=T.int_range(1, 64), default=1, help="CAN buses (slcan/can); chips split in link "
                                                           "blocks across them (default 1)")
    p.add_argument("--gateways", type=T.int_range(1, 64), default=1, metavar="N",
                   help="pty: N serial gateways, each on its own pty with a contiguous block of the links "
                        "(a sheet too big for one UART); gateway 0 leads SYNC with --rate (default 1)")
    p.add_argument("--can-interface", default="virtual",
                   help="python-can interface for --transport can (default virtual)")
    p.add_argument("--channel", action="append",
                   help="python-can channel per bus (repeat); default capsheet0, capsheet1, ...")
    p.add_argument("--fd", action="store_true", help="CAN FD chips and buses")
    p.add_argument("--packed", action="store_true",
                   help="the gateway answers SYNC with SNAPSHOT frames (serial, or CAN FD); it is then a node "
                        "on the wire that says so (docs/protocol.md §13), and the host learns it")
    p.add_argument("--rate", type=T.rate, default=None, metavar="HZ",
                   help="the gateway generates SYNC at this rate and refuses the host's (one SYNC source per "
                        "segment, §13.3); the host then follows it. Without it the host drives SYNC (the printed "
                        f"command: {HOST_RATE_HZ:g} Hz where the link carries it)")
    p.add_argument("--baud", type=T.positive_int, default=12_000_000,
                   help="pty: the UART rate the virtual gateway stands for (a pty has none), used for the "
                        "capacity check and printed in the host command (default 12000000)")
    p.add_argument("--bitrate", type=T.positive_int, default=1_000_000,
                   help="CAN: the nominal bit rate the virtual bus stands for (default 1000000; CAN FD data 8x)")
    p.add_argument("--noise", type=T.noise, default=0.02, help="sensor noise, %% of g per axis (default 0.02)")
    p.add_argument("--chip-errors", choices=("none", "realistic"), default="none",
                   help="per-chip bias, scale and misalignment: none (ideal, factory calibrated; default) or "
                        "realistic (30 mg, 1.5 %%, 1.5° per axis, uncalibrated; seeded by --seed; "
                        "docs/calibration.md). Use --shape board for the calibration poses")
    p.add_argument("--faults", default="", help="fault spec (see below)")
    p.add_argument("--seed", type=T.seed, default=0, help="seed of uids, chip errors and noise (default 0)")
    p.add_argument("--layout-out", metavar="FILE", type=T.output_file(".csv", ".json", what="a layout file",
                                                                        protect=False),
                   help="write the uid,link layout (CSV, or JSON if .json); an existing file that differs "
                        "needs --overwrite")
    p.add_argument("--symlink", metavar="PATH", type=T.symlink_path,
                   help="pty/slcan: publish the port under this stable path (a symlink; with --bus-count N or "
                        "--gateways N, PATH0..PATHN-1). Only a capsheet sheet's own stale symlink is replaced; "
                        "anything else there needs --overwrite")
    T.add_overwrite_arg(p, "files at --layout-out and --symlink")
    g = p.add_argument_group("layout learning (capsheet layout learn)")
    g.add_argument("--poses", choices=("learn",), default=None,
                   help="take the sheet through the poses of `capsheet layout learn` on a timer, over and over "
                        "(flat, ramp, hump across the rows, hump across the columns; replaces --shape)")
    g.add_argument("--pose-hold-s", type=T.bounded_float(0.5, 600.0), default=3.0, metavar="S",
                   help="--poses: seconds each pose is held (default 3)")
    g.add_argument("--pose-move-s", type=T.bounded_float(0.1, 60.0), default=1.0, metavar="S",
                   help="--poses: seconds spent moving between poses (default 1)")
    g.add_argument("--shuffle-ids", action="store_true",
                   help="put the chips' uids on the links in a seeded random order: a layout a host must learn "
                        "(only --layout-out tells it)")
    p.add_argument("--firmware", choices=("python", "c"), default="python",
                   help="chip implementation: the Python model or the C reference firmware (SIL)")
    p.add_argument("--part", choices=("icm42688p", "icm42688p+mmc5983ma"), default=None,
                   help="with --firmware c: every chip reads these real parts through their C drivers over an "
                        "emulated SPI bus (firmware_ref/part_chip.py), the parts' register emulators fed by "
                        "the sheet's truth; icm42688p: TDK ICM-42688-P (--sensors accel or accel+gyro); "
                        "icm42688p+mmc5983ma: and a MEMSIC MMC5983MA magnetometer (--sensors accel+gyro+mag)")
    p.add_argument("--duration", type=T.duration, default=None, help="stop after this many seconds")
    p.add_argument("-v", "--verbose", action="store_true", help="print every frame sent and received")
    p.set_defaults(func=run)
    return p


def _channels(args) -> list[str] | None:
    if args.channel:
        return list(args.channel)
    if args.transport == "can" and args.can_interface == "udp_multicast":
        return [f"239.74.163.{2 + b}" for b in range(args.bus_count)]
    return None


_SENSOR_FMT = {"accel": 0, "accel+gyro": 1, "accel+gyro+mag": 2}


def _capacity(args, sheet, dev) -> tuple[list[str], list[str], float | None]:
    """(errors, warnings, highest rate the busiest bus carries) for this sheet's own traffic."""
    from protocol.capacity import bus_load
    kind = "serial" if args.transport in ("pty", "memory") else "can"
    if args.transport == "memory" or (args.transport == "can" and args.can_interface == "virtual"):
        return [], [], None
    bitrate = args.baud if kind == "serial" else args.bitrate
    per_bus = [len(b) for b in getattr(dev, "blocks", [range(sheet.n_links)])]
    n = max(per_bus)
    fmt = _SENSOR_FMT[args.sensors]
    load1 = bus_load(n, 1.0, kind=kind, bitrate=bitrate, fd=args.fd, packed=args.packed, fmt=fmt)
    max_rate = 1.0 / load1
    errors, warnings = [], []
    if args.rate is not None:
        load = bus_load(n, args.rate, kind=kind, bitrate=bitrate, fd=args.fd, packed=args.packed, fmt=fmt)
        what = (f"{n} chips per bus at {args.rate:g} Hz need {100 * load:.0f} % of a "
                f"{bitrate / 1e6:g} Mbit/s {'UART' if kind == 'serial' else 'CAN FD' if args.fd else 'CAN'} bus")
        if load > 1.0:
            from host.cli.transport_args import split_needed
            from host.session.core import capacity_remedy
            now = len(per_bus)
            opt = "--gateways" if kind == "serial" else "--bus-count"
            can_split = kind == "can" or args.transport == "pty"

            def fits(packed: bool, fd: bool, start: int):
                return split_needed(sheet.n_links, args.rate, kind=kind, bitrate=bitrate, packed=packed, fd=fd,
                                    start=start, fmt=fmt) if can_split or start == now else None
            more = fits(args.packed, args.fd, now + 1)
            pack_opts = "--packed" if kind == "serial" else "--fd --packed"
            already = args.packed and (kind == "serial" or args.fd)
            k_packed = None if already else fits(True, True, now)
            pack = None if k_packed is None else pack_opts if k_packed == now else f"{pack_opts} {opt} {k_packed}"
            remedy = capacity_remedy(kind, load, args.rate, packed=already or pack is None, fd=already or pack is None,
                                     bitrate=bitrate, pack=pack, split=f"{opt} {more}" if more else None)
            errors.append(f"--rate {args.rate:g} is over capacity: {what}; {remedy}")
        elif load > 0.8:
            warnings.append(f"near capacity: {what}")
    return errors, warnings, max_rate


def host_rate(args, max_rate: float | None) -> float:
    """The SYNC rate the printed host command uses: the sheet's own (--rate, the host follows it),
    else `HOST_RATE_HZ` where the link carries it, else the highest whole rate it carries."""
    if args.rate is not None:
        return args.rate
    if max_rate is None or max_rate >= HOST_RATE_HZ:
        return HOST_RATE_HZ
    return float(max(1, math.floor(max_rate)))


def host_command(args, dev, max_rate: float | None = None) -> str:
    """The exact ``capsheet host`` command that reaches this sheet (printed at start): its ports,
    link rate, lattice, layout, SYNC source and rate, packing."""
    cmd = ["capsheet", "host"]
    if args.transport == "pty":
        for pth in getattr(dev, "paths", [dev.path]):
            cmd += ["--port", pth]
        cmd += ["--baud", str(args.baud)]
    elif args.transport == "slcan":
        for pth in dev.paths:
            cmd += ["--can", f"slcan:{pth}"]
        cmd += ["--bitrate", str(args.bitrate)]
    elif args.transport == "can":
        for ch in dev.channels:
            cmd += ["--can", f"{args.can_interface}:{ch}"]
    else:
        return ""
    if args.fd:
        cmd.append("--fd")
    lat = args.lattice
    cmd += ["--lattice", lat if isinstance(lat, str) else f"{lat.rows}x{lat.cols}"]
    if args.layout_out:
        cmd += ["--layout", args.layout_out]
    else:
        cmd.append("--auto-assign")
    if args.rate is not None:  # the gateway says it drives SYNC (§13.3); a driving host would refuse
        cmd += ["--sync", "follow"]
    cmd += ["--rate", f"{host_rate(args, max_rate):g}"]
    if getattr(args, "sensors", "accel") != "accel":
        cmd += ["--sensors", args.sensors]
    # no --packed: the gateway node says it packs (GATEWAY_INFO), the host learns it
    return shlex.join(cmd)


def write_layout(sheet, path: str, *, overwrite: bool = False) -> str | None:
    """Write ``sheet``'s layout to ``path``; a file already there is kept when it holds the same
    layout (a sheet started again with the same seed) and replaced only with ``overwrite`` when it
    differs (someone's layout of a real sheet). Returns why it was not written, or None."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".layout-", suffix=os.path.splitext(path)[1], dir=folder)
    os.close(fd)
    try:
        sheet.write_layout(tmp)
        if os.path.lexists(path):
            if os.path.isfile(path) and filecmp.cmp(tmp, path, shallow=False):
                return None  # the same layout: nothing to change
            if not overwrite:
                return f"{path} exists and holds another layout: add --overwrite to replace it, or give another name"
        os.replace(tmp, path)
        tmp = None
        return None
    finally:
        if tmp is not None:
            os.unlink(tmp)


def _fmt_frame(frame) -> str:
    from protocol.can import CanFrame, decode_can
    from protocol.framing import decode_frame
    from virtual_sheet.faults import ERROR_FRAME
    if frame is ERROR_FRAME:
        return "<error frame>"
    if isinstance(frame, CanFrame):
        return f"{frame.arbitration_id:08X}#{frame.data.hex()}  {decode_can(frame.arbitration_id, frame.data, is_fd=frame.is_fd)}"
    return str(decode_frame(bytes(frame).rstrip(b"\x00")))


def make_device(args, verbose=None):
    """The sheet and its device from parsed arguments."""
    from virtual_sheet.faults import FaultSpec
    from virtual_sheet.sheet import VirtualSheet
    transport = "can" if args.transport in ("can", "slcan") else "serial"
    spec = FaultSpec.parse(args.faults)
    from virtual_sheet.sensor import chip_error_model
    sensor = chip_error_model(getattr(args, "chip_errors", "none"), noise_pct_g=args.noise, chip_seed=args.seed)
    sensors = getattr(args, "sensors", "accel")
    if sensors != "accel" and args.packed and args.transport in ("can", "slcan") and not args.fd:
        raise ValueError(f"--sensors {sensors} with --packed on classic CAN: SNAPSHOT_IMU needs CAN FD "
                         "(docs/protocol.md §16.5: classic CAN cannot carry it); add --fd, or drop --packed")
    factory = load_chip_factory(args.firmware)
    part = getattr(args, "part", None)
    if part is not None:
        if args.firmware != "c":
            raise ValueError(f"--part {part} needs --firmware c (the C driver reads the part)")
        factory = part_chip_factory(part)
    scene = None
    if getattr(args, "poses", None) == "learn":
        from virtual_sheet.layout_poses import LayoutPoseScene
        lat = args.lattice
        scene = LayoutPoseScene(lat.rows, lat.cols, args.link_length, hold_s=args.pose_hold_s,
                                move_s=args.pose_move_s, seed=args.seed)
    sheet = VirtualSheet("layout poses" if scene is not None else args.shape, args.lattice,
                         link_length=args.link_length, noise=args.noise, scene=scene,
                         sensor=sensor, seed=args.seed, transport=transport, fd=args.fd,
                         chip_factory=factory, faults=spec, sensors=sensors,
                         shuffle_ids=bool(getattr(args, "shuffle_ids", False)))
    if part is not None:
        factory.bind(sheet)  # the parts read the sheet's truth
    kw = dict(packed=args.packed, sync_rate_hz=args.rate, verbose=verbose)
    if args.symlink and args.transport in ("pty", "slcan"):
        from virtual_sheet.devices import claim_symlink
        n = args.gateways if args.transport == "pty" else args.bus_count
        for pth in [args.symlink] if n == 1 else [f"{args.symlink}{b}" for b in range(n)]:
            try:
                claim_symlink(pth, replace=bool(getattr(args, "overwrite", False)))
            except FileExistsError as exc:
                raise ValueError(f"--symlink {exc}") from None
    if args.transport == "pty" and getattr(args, "gateways", 1) > 1:
        from virtual_sheet.devices import MultiPtyDevice
        paths = [f"{args.symlink}{b}" for b in range(args.gateways)] if args.symlink else None
        dev = MultiPtyDevice(sheet, n_gateways=args.gateways, symlink_paths=paths, **kw)
    elif args.transport == "pty":
        from virtual_sheet.devices import PtyDevice
        dev = PtyDevice(sheet, symlink_path=args.symlink, **kw)
    elif args.transport == "memory":
        from virtual_sheet.devices import MemoryDevice
        dev = MemoryDevice(sheet, **kw)
    elif args.transport == "slcan":
        from virtual_sheet.slcan import SlcanDevice
        paths = None
        if args.symlink:
            paths = [args.symlink] if args.bus_count == 1 else [f"{args.symlink}{b}" for b in range(args.bus_count)]
        dev = SlcanDevice(sheet, n_buses=args.bus_count, symlink_paths=paths, **kw)
    else:
        from virtual_sheet.devices import CanDevice
        dev = CanDevice(sheet, n_buses=args.bus_count, interface=args.can_interface, channels=_channels(args), **kw)
    return sheet, dev


def run(args) -> int:
    out = sys.stdout

    def verbose(direction, frame):
        try:
            if direction == "rx" and isinstance(frame, (bytes, bytearray)):
                print(f"rx {bytes(frame).hex()}", file=out)
            else:
                print(f"{direction} {_fmt_frame(frame)}", file=out)
        except (OSError, ValueError):  # stdout closed (e.g. piped into head): keep the sheet running
            pass

    if getattr(args, "poses", None) and getattr(args, "sensors", "accel") != "accel":
        print("capsheet virtual: --poses learn runs the layout poses on accelerometer chips: drop --sensors",
              file=sys.stderr)
        return 2
    if getattr(args, "gateways", 1) > 1 and args.transport != "pty":
        print("capsheet virtual: --gateways is for --transport pty (serial gateways); for CAN use "
              "--bus-count", file=sys.stderr)
        return 2
    try:
        sheet, dev = make_device(args, verbose if args.verbose else None)
    except (ValueError, RuntimeError, OSError) as exc:  # a bad shape or fault spec, a path not ours
        print(f"capsheet virtual: {exc}", file=sys.stderr)
        return 2
    errors, warnings, max_rate = _capacity(args, sheet, dev)
    if errors:
        for e in errors:
            print(f"capsheet virtual: {e}", file=sys.stderr)
        return 2
    for w in warnings:
        print(f"capsheet virtual: {w}", file=sys.stderr)

    def on_signal(signum, frame):  # SIGTERM/SIGHUP: leave through `finally` (symlinks removed)
        raise KeyboardInterrupt
    for sig in (signal.SIGTERM, signal.SIGHUP):
        try:
            signal.signal(sig, on_signal)
        except (ValueError, OSError):  # not the main thread
            pass
    if args.layout_out:
        why = write_layout(sheet, args.layout_out, overwrite=args.overwrite)
        if why:
            print(f"capsheet virtual: --layout-out {why}", file=sys.stderr)
            return 2
    try:
        # inside the try whose `finally` stops the device: a SIGTERM/SIGHUP that lands while it is
        # starting (its symlink already published) still stops it and removes the symlink
        try:
            dev.start()
        except Exception as exc:  # noqa: BLE001 - a port or bus that cannot be opened: one line
            print(f"capsheet virtual: cannot start the {args.transport} device: {exc}", file=sys.stderr)
            return 1
        print(f"capsheet virtual: {sheet!r}", file=out)
        print(f"connect to: {dev.describe()}", file=out)
        cmd = host_command(args, dev, max_rate)
        if cmd:
            print(f"  {cmd}", file=out)
        elif args.transport == "can" and args.can_interface == "virtual":
            pass
        if args.transport == "can" and args.can_interface == "virtual":
            print("  note: python-can's 'virtual' interface reaches only this process; use --transport "
                  "slcan, or --can-interface udp_multicast / socketcan, for a host in another process",
                  file=out)
        if max_rate is not None:
            print(f"capacity: this link carries this sheet's traffic up to {max_rate:.0f} Hz", file=out)
        if args.layout_out:
            print(f"layout written to {args.layout_out}", file=out)
        out.flush()
        t_end = None if args.duration is None else time.monotonic() + args.duration
        last = {}
        while t_end is None or time.monotonic() < t_end:
            time.sleep(1.0 if t_end is None else max(0.0, min(1.0, t_end - time.monotonic())))
            if dev.error is not None:
                print(f"capsheet virtual: device thread failed: {dev.error!r}", file=sys.stderr)
                return 1
            st = {k: sum(g.stats.as_dict()[k] for g in dev.gateways)
                  for k in ("host_frames", "syncs", "frames_to_host", "snapshots")}
            d = {k: st[k] - last.get(k, 0) for k in st}
            last = st
            streaming = sum(1 for c in sheet.chips if int(getattr(c, "state", 0)) == 2)
            faults = sheet.fault_stats.nonzero()
            line = (f"t={dev.now():7.1f}s  sync {d['syncs']}/s  sent {d['frames_to_host']} frames/s"
                    + (f" ({d['snapshots']} snapshots)" if args.packed else "")
                    + f"  host frames {d['host_frames']}/s  streaming {streaming}/{sheet.n_links}"
                    + ("  [bus down]" if dev.down else "")
                    + (f"  faults {faults}" if faults else ""))
            print(line, file=out, flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        dev.stop()
    return 0
