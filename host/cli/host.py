"""``capsheet host``: connect to a sheet, bring it up from whatever state it is in, stream, show a
live status line, record snapshots and end with a summary whose exit status tells the truth
(docs/host.md).

    capsheet host --port /dev/pts/5 --lattice 14x14 --layout sheet.csv --rate 100 --record run.mcap --live
    capsheet host --can virtual:bus0 --can virtual:bus1 --lattice 14x14 --duration 10
    capsheet host --can slcan:/dev/pts/6 --bitrate 1000000 --auto-assign
    capsheet host --port /tmp/sheet0 --port /tmp/sheet1 --baud 12000000 --layout sheet.json

Several --port (a sheet behind several serial gateways, each with a block of its links) or several
--can (buses) are merged into one lattice: each chip is known on the port it answers on. In drive
mode the host sends every SYNC on every port; with a gateway driving SYNC (--sync follow) each port
carries it. Gateway nodes (docs/protocol.md §13) are discovered with the chips and assigned node ids
from 0x7FFF down: the host learns from them which ports pack SNAPSHOTs and which gateway drives SYNC.

Each port is this session's alone: a port another session holds is refused at once (exit 1, one
line naming the holder), and a port that goes away is reopened only when the same device is back
at its path. Without --lattice (and a JSON layout) the sheet is asked first: its gateways' tables
or a CSV layout's links name the lattice when one fits, else the host says what answered and which
lattices fit (exit 2). A big sheet at a high rate gets reader processes and an estimator process
unasked (--no-reader-processes, --no-estimate-process keep them in this process).

The status line (and the summary, and --json) gives completeness twice, over the same snapshots:
by snapshot (every expected link arrived) and by valid link sample over the lattice's links (what
--min-complete judges: a dead or absent chip lowers it while the snapshots stay complete).

Exit status: 0 the run met ``--min-complete``; 1 no chip found, none streamed, completeness below
``--min-complete``, the port failed or is in use by another session, a port came back as another
device, or another SYNC source stopped a driving host; 2 a usage error
or a mismatch found before streaming (bad value, malformed layout, layout vs lattice, CAN FD frames
on a classic bus, layout chips that never answer, over capacity, a port given twice, the same chips
on two ports, a port of another sheet, no --lattice and the answers do not name one).

The Python API is `host.session.core.Host` (re-exported here).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time

from host.cli import argtypes as T
from host.session.core import CapacityError, Host, Layout, MismatchError, SessionError, SyncConflictError, link_ranges
from host.cli.record_args import SessionOutputs, add_record_args
from host.cli.transport_args import add_transport_args, check_ports, open_transports
from host.cli.sensor_args import add_sensor_args, imu_config
from host.cli.timing_args import add_timing_args, timing_kwargs
from host.transport.ports import TransportError
from protocol.lattice import Lattice
from protocol.layout import LayoutError

__all__ = ["register", "run", "Host", "Layout", "open_transports", "StatusLine"]

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def register(subparsers) -> None:
    p = subparsers.add_parser("host", help="talk to a sheet: discover, assign, stream, record",
                              description=__doc__.split("\n\n")[0],
                              epilog=__doc__.split("\n\n", 2)[2].split("\n\nThe Python API")[0],
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    add_transport_args(p, title="transports (one or more --port, or one or more --can)")
    p.add_argument("--reader-processes", action=argparse.BooleanOptionalAction, default=None,
                   help="read every --port through a small process of its own that drains the port into a "
                        "1 MB pipe (host/transport/portreader.py): a tty gives 4 KB a read, and five gateways "
                        "read by threads of one interpreter fall behind at 145 Hz. Default: chosen for the "
                        "sheet, on when its links x --rate reach 500,000 link samples a second (64x64 at "
                        "145 Hz: 1.17 M; 32x32: 0.29 M) and the ports are device paths (docs/host.md)")
    # -- the session's arguments: one block ------------------------------------------
    p.add_argument("--lattice", type=T.lattice, default=None,
                   help="joints ROWSxCOLS (default: a JSON layout's; else a CSV layout's links, or the "
                        "sheet's own gateways' tables, when exactly one lattice has that many links; "
                        "else the host says which lattices fit what answered and stops, exit 2)")
    p.add_argument("--layout", type=T.existing_file(".csv", ".json", what="a layout file"),
                   help="uid -> link file (CSV 'uid,link' or JSON; uids in hex; docs/host.md)")
    p.add_argument("--auto-assign", action="store_true",
                   help="without --layout: place chips on links in uid order (positions arbitrary)")
    p.add_argument("--allow-missing", action="store_true",
                   help="stream even if layout chips never answer or chips not in the layout announce "
                        "(default: a mismatch, exit 2)")
    p.add_argument("--rate", type=T.rate, default=100.0, help="SYNC rate in Hz, 0 < rate <= 4000 (default 100)")
    p.add_argument("--sync", choices=("drive", "follow", "auto"), default="drive",
                   help="drive SYNC from the host (default; another SYNC source — a gateway that says it "
                        "generates SYNC, or SYNC frames heard — is an error), follow a gateway's SYNC, or auto: "
                        "drive unless another source is found, then follow it")
    p.add_argument("--packed", action="store_true",
                   help="check every port's capacity for SNAPSHOT frames (an override: a gateway node that "
                        "packs says so, docs/protocol.md §13, and its port is checked for SNAPSHOTs anyway)")
    p.add_argument("--ignore-capacity", action="store_true",
                   help="stream even when the traffic exceeds a bus's capacity (default: refuse, exit 2)")
    p.add_argument("--deadline-ms", type=T.bounded_float(0.0, 60_000.0, lo_open=True, unit="ms"), default=None, help="wait this long for missing links")
    p.add_argument("--no-input-hold", action="store_true",
                   help="give an incomplete counter up at its deadline even when its bus was not read past it "
                        "yet (a host that was not scheduled for a while; the behaviour before the input watermark: "
                        "host.snapshots.aggregator, 'Input watermark')")
    p.add_argument("--duration", type=T.duration, default=None, help="stop after this many seconds")
    p.add_argument("--discover-s", type=T.bounded_float(0.0, 60.0, lo_open=True, unit="s"), default=0.5, help="discovery window per round (s; 0.25 at least until a first chip answered); it lasts while new chips are still answering (until 0.25 s pass without one, at most 20 windows)")
    p.add_argument("--no-reset", action="store_true",
                   help="bring-up without RESET (STOP and drain only): chips keep their state")
    p.add_argument("--min-complete", type=T.percent, default=90.0, metavar="PCT",
                   help="exit 1 if fewer than PCT %% of the lattice's link samples arrived valid (default 90)")
    p.add_argument("--status-every", type=T.bounded_float(0.0, 3600.0, lo_open=True, unit="s"), default=None, metavar="S",
                   help="status period (default 0.5 s on a terminal as one updated line, 5 s as plain lines otherwise)")
    p.add_argument("--json", action="store_true",
                   help="print the final statistics (with the summary under 'summary') as JSON on stdout")
    p.add_argument("--calibration", metavar="CAL_JSON", type=T.existing_file(".json", what="a calibration file"),
                   help="apply this calibration (capsheet calibrate) to every snapshot, and check chip "
                        "health on still stretches (docs/calibration.md)")
    p.add_argument("-q", "--quiet", action="store_true", help="no live status line")
    add_sensor_args(p)
    add_timing_args(p, deadline=True)  # --ack-timeout-ms --watchdog-ms
    add_record_args(p, can_log=True, link_length=True, estimate_process=True)  # --record --live --live-rate --can-log
    # --link-length --estimate-process
    p.set_defaults(func=run)


# ---------------------------------------------------------------------------------------------
# status line: log lines never glue onto it
# ---------------------------------------------------------------------------------------------

class StatusLine:
    """The live status on ``stream``: on a TTY one line rewritten with ``\\r``; a log record first
    ends that line so the two never glue; elsewhere (a pipe, a file) plain lines."""

    def __init__(self, stream, tty: bool | None = None) -> None:
        self.stream = stream
        self.tty = bool(getattr(stream, "isatty", lambda: False)()) if tty is None else tty
        self.open = False  # a \r line is on screen without its newline
        # the status is shown from the main thread, log records come from the host's threads:
        # "end the line, then write the record" and "write the line" must not interleave (under
        # load a record once landed between a status line's write and its ``open = True``)
        self.lock = threading.RLock()

    def show(self, text: str) -> None:
        with self.lock:
            if self.tty:
                self.stream.write("\r" + text + "\x1b[K")
                self.open = True
            else:
                self.stream.write(text + "\n")
            self.stream.flush()

    def end(self) -> None:
        with self.lock:
            if self.open:
                self.stream.write("\n")
                self.stream.flush()
                self.open = False


class _StatusAwareHandler(logging.StreamHandler):
    def __init__(self, status: StatusLine) -> None:
        super().__init__(status.stream)
        self.status = status

    def emit(self, record) -> None:
        with self.status.lock:
            self.status.end()
            super().emit(record)


def completeness_pct(emitted: int, complete: int, valid_links: int, n_links: int) -> tuple[float, float]:
    """(complete snapshots %, valid link samples %) over the same ``emitted`` snapshots: by
    snapshot, complete / emitted; by valid link, valid samples / (emitted x the lattice's links) —
    the figure ``--min-complete`` judges. (0, 0) before any snapshot."""
    if emitted <= 0:
        return 0.0, 0.0
    return 100.0 * complete / emitted, 100.0 * valid_links / (emitted * max(1, n_links))


def _status_text(host: Host, t0: float, n0: int) -> str:
    st = host.aggregator.stats
    dt = max(1e-9, time.monotonic() - t0)
    rate = (st.emitted - n0) / dt
    done, links = completeness_pct(st.emitted, st.complete, st.valid_links, host.lattice.n_links)
    errors = sum(t.stats.error_count for t in host.transports)
    per = max(1, st.emitted * host.lattice.n_links)
    imu = (f"{100.0 * st.imu_links / per:5.1f}% with gyro  " if host.imu_config is not None or st.imu_links else "")
    if st.mag_links:
        imu += f"{100.0 * st.mag_links / per:5.1f}% with mag  "
    return (f"{st.emitted:7d} snapshots {rate:7.1f}/s  complete {done:5.1f}% of snapshots, "
            f"{links:5.1f}% of link samples valid  {imu}"
            f"late {st.late}  stray {st.stray}  dup {st.duplicates}  unknown {st.unknown}  "
            f"dropped {st.dropped}  errors {errors}  silent {len(host.silent_links)}  "
            f"recoveries {host.recoveries}")


def _summary_lines(s: dict, min_pct: float) -> list[str]:
    out = [f"summary: {s['snapshots']} snapshots, {s['complete_snapshots']} complete "
           f"({s['complete_snapshots_pct']:.1f} %); "
           f"{s['valid_links_pct']:.1f} % of the {s['links']} links' samples valid (need {min_pct:g} %)"]
    if "imu_links_pct" in s:
        mag = f", magnetometer {s['mag_links_pct']:.1f} %" if "mag_links_pct" in s else ""
        out.append(f"  IMU records (gyroscope, sample time): {s['imu_links_pct']:.1f} %{mag} of the link samples")
    if s["unassigned_links"]:
        out.append(f"  links without a chip: {len(s['unassigned_links'])} "
                   f"({link_ranges(d['link'] for d in s['unassigned_links'])})")
    if s["missing_links"]:
        names = ", ".join(f"{d['link']}" + (f" (uid {d['uid']})" if d["uid"] else "") for d in s["missing_links"][:8])
        more = f" and {len(s['missing_links']) - 8} more" if len(s["missing_links"]) > 8 else ""
        out.append(f"  missing links (silent or absent from most snapshots): {names}{more}")
    if s["errors"]:
        out.append("  errors: " + ", ".join(f"{k} {v}" for k, v in sorted(s["errors"].items())))
    out.append(f"  reconnects {s['reconnects']}, recoveries {s['recoveries']} ({s['recovered_chips']} chips), "
               f"stray frames {s['stray_frames']}, resyncs {s['resyncs']}, late {s['late']}, "
               f"foreign SYNC {s['foreign_syncs']} (sync {s['sync_mode']})")
    for why in s["not_a_sheet"]:
        out.append(f"  {why}")
    if s["sync_conflict"]:
        out.append(f"  {s['sync_conflict']}")
    return out


def imu_summary(host: Host, summary: dict, args) -> None:
    """The summary's IMU part (when the chips were asked for IMU records)."""
    st = host.aggregator.stats
    if host.imu_config is None and not st.imu_links:  # (a packing gateway may configure its chips itself, §16.5)
        return
    per = max(1, st.emitted * host.lattice.n_links)
    summary["sensors"] = (args.sensors if host.imu_config is not None
                          else "accel+gyro+mag" if st.mag_links else "accel+gyro")
    summary["imu_links_pct"] = round(100.0 * st.imu_links / per, 2)
    if summary["sensors"].endswith("mag") or st.mag_links:
        summary["mag_links_pct"] = round(100.0 * st.mag_links / per, 2)


def calibration_words(host: Host, up: dict) -> str:
    """The bring-up line's calibration part: chips with a calibration of their own apart from those
    reporting the nominal values (no stored calibration), e.g. ``0 calibrated (364 nominal)``."""
    c = host.calibration_summary()
    unread = up["assigned"] - c["own"] - c["nominal"]
    return (f"{c['own']} calibrated ({c['nominal']} nominal: no calibration of their own"
            + (f"; {unread} did not answer CAL_READ" if unread > 0 else "") + ")")


def _fail(msg: str, code: int) -> int:
    print(f"capsheet host: {msg}", file=sys.stderr)
    return code


#: the snapshots waiting for this command's loop: at least this many seconds of them at --rate
QUEUE_S = 2.0


def queue_size_for(rate_hz: float | None) -> int:
    """The host's snapshot queue (`Host` ``queue_size``): `QUEUE_S` at the SYNC rate, at least the
    library's 64. A following host's chips stream from its bring-up's end, ~1 s before this
    command's loop takes snapshots (the session's documents are written meanwhile): a 64x64 sheet
    at 145 Hz lost 91-112 of ~2,480 snapshots' estimates off a 64-deep queue (recorded at
    emission, never estimated)."""
    return max(64, int(QUEUE_S * float(rate_hz or 0.0)) + 1)


#: link samples a second (links x SYNC rate) from which a sheet is big for one interpreter: its
#: serial ports are read by reader processes and its estimates made in a process of their own.
#: 64x64 on five gateways at 145 Hz (1.17 M) held 0.6-0.9 % complete snapshots in one process and
#: 100 % with both (docs/host.md, "A big sheet at a high rate"); 32x32 on two (0.29 M) holds 145 Hz
#: in one (benchmarks/bench_live.py, 32x32-packed-2gw)
BIG_SHEET_SAMPLES_PER_S = 500_000


def choose_design(args, lattice: Lattice) -> str | None:
    """``--reader-processes`` and ``--estimate-process`` where the command line left them (None):
    on for a big sheet at a high rate (`BIG_SHEET_SAMPLES_PER_S`) — readers when the ports are
    serial device paths (a reader needs a file descriptor), the estimator when estimates are made
    (``--record``, ``--live``, ``--publish``) of accelerometer readings (6/9-axis chips keep their
    fused estimator in this process); off otherwise. Sets both on ``args``; returns the line that
    says what was chosen for the sheet, or None when nothing was left to choose or nothing is on."""
    samples = lattice.n_links * float(args.rate)
    big = samples >= BIG_SHEET_SAMPLES_PER_S
    chosen = []
    if args.reader_processes is None:
        ports = list(getattr(args, "port", None) or [])
        args.reader_processes = bool(big and ports and all("://" not in p for p in ports))
        if args.reader_processes:
            chosen.append("each port read by a process of its own")
    if getattr(args, "estimate_process", False) is None:
        estimates = bool(args.record or args.live is not None or args.publish is not None)
        args.estimate_process = bool(big and estimates and getattr(args, "sensors", "accel") == "accel")
        if args.estimate_process:
            chosen.append("the estimates made in a process of their own")
    if not chosen:
        return None
    return (f"a big sheet at a high rate ({lattice.n_links} links x {float(args.rate):g} Hz = {samples / 1e6:.2f} M "
            f"link samples a second): {' and '.join(chosen)} (--no-reader-processes / --no-estimate-process "
            f"keep them in this process)")


def _lattice_from_the_sheet(transports, args) -> tuple[Lattice | None, int]:
    """Without ``--lattice`` (and a layout that names one): ask every port who is there (a broadcast
    GET_INFO, read-only: `host.transport.discover.ask`), say what answered, and take the lattice only
    when the gateways' tables decide it (`host.cli.lattice_choice.choose`); else one line, exit 2
    (exit 1 when nothing answered)."""
    from host.cli.lattice_choice import choose
    from host.transport.discover import ask
    chips: set[int] = set()
    runs: list[tuple[int, int]] = []
    budget = max(2.0, 4 * args.discover_s)
    for t in transports:
        try:
            c = ask(t, budget)
        except TransportError as exc:
            return None, _fail(str(exc), EXIT_FAIL)
        r = c.result()
        chips.update(int(u, 16) for u in r.chip_uids)
        runs += [(g.first_link, g.link_count) for gw in c.gw_runs.values() for g in gw.values()]
    names = ", ".join(t.name for t in transports)
    if not chips and not runs:
        return None, _fail(f"no --lattice, and no chip answered on {names} (is the sheet powered and the "
                           f"port right?)", EXIT_FAIL)
    picked, why = choose(len(chips), runs)
    if picked is None:
        return None, _fail(f"no --lattice: {why}", EXIT_USAGE)
    print(f"capsheet host: no --lattice: {why}", file=sys.stderr)
    return Lattice(*picked), EXIT_OK


def run(args) -> int:
    from host.cli import short_gil_switch
    short_gil_switch()  # the SYNC thread gets the interpreter lock within 0.5 ms, not 5 ms
    status = StatusLine(sys.stderr)
    if args.status_every is None:
        args.status_every = 0.5 if status.tty else 5.0
    # the run's warnings go through its own status line, and only while it runs: a handler left by an
    # earlier run in this process (a program calling the entry point twice) would write them to that
    # run's stream, which may be gone
    root = logging.getLogger()
    for old in [x for x in root.handlers if isinstance(x, _StatusAwareHandler)]:
        root.removeHandler(old)
    handler = _StatusAwareHandler(status)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    try:
        return _run(args, status)
    finally:
        root.removeHandler(handler)


def _run(args, status: StatusLine) -> int:
    # -- everything checkable before a port is opened: one line, exit 2 --------------------------
    check_ports(args, prog="capsheet host")  # neither or both of --port/--can, a port given twice
    if args.reader_processes and not getattr(args, "port", None):
        return _fail("--reader-processes reads serial ports (--port); python-can reads --can buses itself", EXIT_USAGE)
    layout = None
    if args.layout:
        try:
            layout = Layout.load(args.layout)
        except (LayoutError, ValueError) as exc:
            return _fail(f"bad --layout: {exc}", EXIT_USAGE)
    lattice = args.lattice
    if layout is not None and layout.lattice is not None:
        from_layout = Lattice.parse(layout.lattice)
        if lattice is None:
            lattice = from_layout
        elif (lattice.rows, lattice.cols) != (from_layout.rows, from_layout.cols):
            return _fail(f"--lattice {lattice.rows}x{lattice.cols} but the layout {args.layout} is for "
                         f"{layout.lattice}: give the matching lattice (or leave --lattice out)", EXIT_USAGE)
    if lattice is None and layout is not None:  # a layout without a lattice: its links are the sheet's table
        from host.cli.lattice_choice import choose
        picked, why = choose(None, layout_links=max(layout.links.values(), default=-1) + 1)
        if picked is None:
            return _fail(why, EXIT_USAGE)
        print(f"capsheet host: no --lattice: {why}", file=sys.stderr)
        lattice = Lattice(*picked)
    if layout is not None:
        far = sorted((k, u) for u, k in layout.links.items() if k >= lattice.n_links)
        if far:
            k, u = far[0]
            return _fail(f"the layout {args.layout} puts {len(far)} chip(s) beyond lattice {lattice.rows}x"
                         f"{lattice.cols} ({lattice.n_links} links), e.g. uid 0x{u:016X} on link {k}", EXIT_USAGE)
        if len(layout.links) < lattice.n_links:
            print(f"capsheet host: the layout names {len(layout.links)} chips for {lattice.n_links} links; "
                  f"{lattice.n_links - len(layout.links)} links have no chip (counted as missing)", file=sys.stderr)
    cal = None
    if lattice is not None:
        from host.cli.calibrate import load_calibration_arg
        cal = load_calibration_arg(args.calibration, lattice, "capsheet host")
    if layout is None and not args.auto_assign:
        print("capsheet host: no --layout given; auto-assigning chips in uid order (positions arbitrary). "
              "Pass --auto-assign to silence this.", file=sys.stderr)
    design = None
    readers_given = args.reader_processes
    if lattice is not None:
        design = choose_design(args, lattice)
    else:
        args.reader_processes = bool(args.reader_processes)  # the probe reads in this process
    try:
        transports = open_transports(args, prog="capsheet host")
    except TransportError as exc:
        return _fail(str(exc), EXIT_FAIL)
    if lattice is None:  # nobody named it: ask the sheet (lattice_choice says when its answers decide)
        lattice, code = _lattice_from_the_sheet(transports, args)
        if lattice is None:
            for t in transports:
                t.close()
            return code
        from host.cli.calibrate import load_calibration_arg
        try:
            cal = load_calibration_arg(args.calibration, lattice, "capsheet host")
        except SystemExit:
            for t in transports:
                t.close()
            raise
        args.reader_processes = readers_given
        design = choose_design(args, lattice)
        if args.reader_processes and not readers_given:  # chosen now: the ports again, through readers
            for t in transports:
                t.close()
            try:
                transports = open_transports(args, prog="capsheet host")
            except TransportError as exc:
                return _fail(str(exc), EXIT_FAIL)
    if design is not None:
        print(f"capsheet host: {design}", file=sys.stderr)
    try:
        host = Host(transports, lattice, layout=layout, rate_hz=args.rate, sync=args.sync,
                    deadline_s=None if args.deadline_ms is None else args.deadline_ms / 1000,
                    queue_size=queue_size_for(args.rate), **timing_kwargs(args))
    except (MismatchError, ValueError) as exc:
        for t in transports:
            t.close()
        return _fail(str(exc), EXIT_USAGE)
    host.imu_config = imu_config(args)
    host.aggregator.hold_for_input = not args.no_input_hold
    # what the host waits for, as it runs (a default follows the rate and the deadline): --json says
    waits = {"ack_timeout_ms": round(1e3 * host.timeout_s, 3), "watchdog_ms": round(1e3 * host.watchdog_s, 3)}

    def on_term(signum, frame):  # SIGTERM: stop the sheet as Ctrl-C does
        raise KeyboardInterrupt
    try:
        signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not the main thread (an embedding program): leave its handler alone
        pass

    out = SessionOutputs(args, host.lattice, args.link_length, mode="host", colour_by="links",
                         prog="capsheet host")
    out.attach(host)
    writer = out if out.active else None
    stats: dict | None = None
    code = EXIT_OK
    summary: dict | None = None
    if cal is not None:  # before bring-up: the first snapshot streamed is corrected too
        host.set_calibration(cal)
    try:
        with host:
            try:
                up = host.bring_up(args.discover_s, reset=not args.no_reset, strict=not args.allow_missing,
                                   capacity="warn" if args.ignore_capacity else "refuse", packed=args.packed)
            except (MismatchError, SyncConflictError) as exc:
                return _fail(str(exc), EXIT_USAGE)
            print(f"capsheet host: {up['discovered']} chips found, {up['assigned']} assigned, "
                  f"{up['configured']} configured, {calibration_words(host, up)}, "
                  f"{up['started']} started on {', '.join(t.name for t in transports)}", file=sys.stderr)
            if up["discovered"] == 0:
                return _fail(f"no chip answered on {', '.join(t.name for t in transports)} "
                             f"(is the sheet powered and the port right?)", EXIT_FAIL)
            if up["started"] == 0:
                return _fail("no chip started streaming", EXIT_FAIL)
            if cal is not None:
                from host.snapshots.health import HealthChecker
                host.health = HealthChecker(host.lattice.rows, host.lattice.cols)
            out.describe(host)
            from host.memory import probe_from_env
            probe = probe_from_env(lambda: {k: host.aggregator.stats.summary().get(k) for k in
                                            ("emitted", "complete", "incomplete", "late", "deadline_changes", "late_raises")}
                                   | {"deadline_ms": round(1e3 * host.aggregator.deadline_s, 2)})  # CAPSHEET_MEMORY_PROBE: what grows, the collector's pauses
            t0, n0, last = time.monotonic(), host.aggregator.stats.emitted, time.monotonic()
            end = None if args.duration is None else t0 + args.duration
            while end is None or time.monotonic() < end:
                snap = host.get(0.1)
                for _ in range(256):  # bounded: the duration and the status are checked meanwhile
                    if snap is None or writer is None:
                        break
                    # every queued snapshot is recorded (the recording took each as it was
                    # emitted, corrected), the estimate is made on the newest only
                    newer = host.get(0)
                    writer.snapshot(snap, estimate=newer is None)
                    snap = newer
                if snap is not None and writer is not None:
                    writer.snapshot(snap)
                if writer is not None:
                    writer.poll()  # --estimate-process: its estimates to the outputs
                if host.sync_conflict:
                    code = EXIT_FAIL
                    break
                if host.mismatch:
                    code = EXIT_USAGE
                    break
                now = time.monotonic()
                if not args.quiet and now - last >= args.status_every:
                    status.show(_status_text(host, t0, n0))
                    last = now
            host.stop()
            if probe is not None:
                probe.stop()
            for snap in host.drain():
                if writer is not None:
                    writer.snapshot(snap)
            if not args.quiet:
                status.show(_status_text(host, t0, n0))
                status.end()
            stats = host.stats
            summary = host.summary()
            imu_summary(host, summary, args)
    except KeyboardInterrupt:
        status.end()
        stats = host.stats
        summary = host.summary()
    except SessionError as exc:
        status.end()
        return _fail(str(exc), EXIT_FAIL)
    finally:
        if writer is not None:
            writer.close(stats=stats)
            if summary is not None:
                summary.update(out.output_counts())
    if summary is not None:
        for line in _summary_lines(summary, args.min_complete):
            print(line, file=sys.stderr)
        if summary["snapshots"] == 0 or summary["valid_links_pct"] == 0:
            print("capsheet host: no chip streamed", file=sys.stderr)
            code = EXIT_FAIL
        elif summary["valid_links_pct"] < args.min_complete:
            print(f"capsheet host: completeness {summary['valid_links_pct']:.1f} % is below --min-complete "
                  f"{args.min_complete:g} %", file=sys.stderr)
            code = EXIT_FAIL
        if summary["sync_conflict"] or summary["not_a_sheet"]:
            code = EXIT_FAIL
        if summary["mismatch"]:
            print(f"capsheet host: {summary['mismatch']}", file=sys.stderr)
            code = EXIT_USAGE
    if args.json:
        try:
            print(json.dumps({**(stats or {}), "summary": summary, "exit": code, "waits": waits,
                              "design": {"reader_processes": bool(args.reader_processes),
                                         "estimate_process": bool(args.estimate_process)}},
                             default=str, indent=1))
            sys.stdout.flush()
        except BrokenPipeError:
            pass
    return code
