"""``capsheet estimate --subscribe [zenoh[:ENDPOINT]]``: an estimate worker on Zenoh.

The worker subscribes to the snapshots hosts publish (``capsheet host --publish zenoh``), asks each
sheet's ``capsheet/<sheet>/info`` queryable for its lattice and link length (a late joiner gets them
too), estimates every snapshot of its sheets in the order they came with the estimator the host
uses (`host.analysis.estimator.estimate`, warm-started from the sheet's previous estimate) and
publishes one estimate per snapshot under ``capsheet/<sheet>/estimate``. `host.workers.distribute` does the
per-sheet work without I/O; this module is the Zenoh session, the queue and the summary.

Zenoh's callbacks only queue the payloads (one FIFO for all sheets, its peak reported): a slow
estimate never makes the network drop what the worker was sent, and each sheet's snapshots stay
in order. Memory is bounded by bytes, whatever comes: a payload larger than the largest sheet's is
refused before it is copied, the queue holds at most `MAX_QUEUED_BYTES`, a sheet waiting for its
info at most `MAX_PENDING_BYTES` of checked snapshots (`MAX_PENDING_SHEETS` sheets,
`MAX_PENDING_TOTAL_BYTES` together); what is refused or dropped is counted and makes the exit 1. Estimates are put with congestion control BLOCK: a slow subscriber of the estimates
delays this worker (whose queue holds the snapshots meanwhile) rather than losing one.

Exit status: 0 when every sheet the worker took had its info, no snapshot was lost between the
first and the last it received, and each got its estimate; 1 otherwise (a lost snapshot, an unknown
sheet, no snapshot at all, no Zenoh endpoint reachable); 2 for a usage error.
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import sys
import threading
import time
from collections import deque

__all__ = ["add_subscribe_args", "check_subscribe", "run_worker", "subscribe_arg", "open_session",
           "add_zenoh_config_arg", "zenoh_config_arg"]

PROG = "capsheet estimate"
EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2
#: how often a sheet whose info did not answer is asked again, s
INFO_RETRY_S = 1.0
#: bytes of snapshots kept for a sheet whose info has not answered yet; beyond, its oldest are
#: dropped (counted). By bytes, not by count: 400 junk payloads of 1 MiB took a worker from 80 MB
#: to 627 MB when this was a count.
MAX_PENDING_BYTES = 64 << 20
#: bytes of snapshots kept for all the sheets whose info has not answered yet together; beyond,
#: new ones are dropped (counted)
MAX_PENDING_TOTAL_BYTES = 256 << 20
#: sheets waiting for their info at once; snapshots of further unknown sheets are dropped (counted)
MAX_PENDING_SHEETS = 64
#: bytes received and not yet taken from the worker's queue; beyond, new payloads are dropped
#: (counted: the worker cannot keep up, or is flooded)
MAX_QUEUED_BYTES = 128 << 20


def subscribe_arg(value: str):
    from host.publish.zenoh_pub import parse_publish
    try:
        kind, endpoint = parse_publish(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).replace("--publish", "--subscribe")) from None
    if kind != "zenoh":
        raise argparse.ArgumentTypeError(f"--subscribe {value!r}: workers read capsheet's own keys, give zenoh "
                                         f"or zenoh:ENDPOINT (ros2 is not read)")
    return kind, endpoint


def zenoh_config_arg(value: str) -> str:
    """``--zenoh-config FILE``: a readable regular file of a config's size (read by Zenoh when the
    session opens)."""
    from host.publish.zenoh_session import check_config_file
    try:
        return check_config_file(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_zenoh_config_arg(group) -> None:
    """``--zenoh-config FILE`` (one help text for every command that opens a Zenoh session)."""
    group.add_argument("--zenoh-config", metavar="FILE.json5", type=zenoh_config_arg, default=None,
                       help="a Zenoh config file (JSON5, as zenohd and every Zenoh tool read it) for the session: "
                            "TLS and its CA, user and password, access control, other endpoints "
                            "(docs/distribution.md). Default: the file ZENOH_SESSION_CONFIG_URI names (as "
                            "rmw_zenoh reads it), else ZENOH_CONFIG, else loopback only: 127.0.0.1, no multicast "
                            "scouting, the machine's sessions meeting at tcp/127.0.0.1:7447. "
                            "ZENOH_CONFIG_OVERRIDE='key=value;...' is applied over it")


def _worker_arg(value: str):
    from host.workers.distribute import parse_worker
    try:
        return parse_worker(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _sheets_arg(value: str):
    from host.workers.distribute import parse_sheets
    try:
        return parse_sheets(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_subscribe_args(p) -> None:
    from host.cli import argtypes as T
    g = p.add_argument_group("estimate worker on Zenoh (--subscribe; docs/distribution.md \"Estimate workers\")")
    g.add_argument("--subscribe", metavar="zenoh[:ENDPOINT]", nargs="?", const=("zenoh", None), default=None,
                   type=subscribe_arg,
                   help="be a worker: estimate the snapshots hosts publish (capsheet host --publish zenoh) and "
                        "publish one estimate per snapshot under capsheet/<sheet>/estimate. zenoh: peer mode on "
                        "loopback only (127.0.0.1, no multicast; the machine's sessions meet at "
                        "tcp/127.0.0.1:7447); zenoh:ENDPOINT: client of the router at that locator, e.g. "
                        "zenoh:tcp/192.168.1.10:7447")
    g.add_argument("--sheets", metavar="NAME,...", type=_sheets_arg, default=None,
                   help="take these sheets only: names, each of which must answer capsheet/<sheet>/info within "
                        "--wait (else: unknown sheet, exit 1), or patterns with * and ? (e.g. 'left_*'), taken "
                        "as they publish. Default: every sheet that publishes snapshots")
    g.add_argument("--worker", metavar="I/N", type=_worker_arg, default=None,
                   help="one of N workers, index I (0..N-1): of the sheets selected, take those whose CRC-32 of "
                        "the name modulo N is I, so N workers given 0/N .. N-1/N share them, each sheet to one "
                        "of them, without a coordinator")
    g.add_argument("--duration", type=T.duration, default=None, metavar="S",
                   help="stop after S seconds (default: until interrupted, or --idle)")
    g.add_argument("--idle", type=T.duration, default=None, metavar="S",
                   help="stop when no snapshot has come for S seconds after the first one (the hosts ended)")
    g.add_argument("--wait", type=T.duration, default=10.0, metavar="S",
                   help="how long the sheets named by --sheets have to answer their info query at start, "
                        "seconds (default 10)")
    add_zenoh_config_arg(g)


def check_subscribe(ns) -> str | None:
    """Usage errors between the two modes (one line, exit 2)."""
    if ns.subscribe is None:
        for flag, v in (("--sheets", ns.sheets), ("--worker", ns.worker), ("--idle", ns.idle),
                        ("--duration", ns.duration)):
            if v is not None:
                return f"{flag} is for an estimate worker (--subscribe)"
        if not ns.recording:
            return "give a recording (and --out), or --subscribe to be an estimate worker"
        if ns.out is None:
            return "the following arguments are required: --out"
        return None
    if ns.recording:
        return "--subscribe takes no recording: the snapshots come from Zenoh"
    for flag, v in (("--out", ns.out), ("--png", ns.png), ("--from-raw", ns.from_raw or None),
                    ("--lattice", ns.lattice), ("--link-length", ns.link_length)):
        if v is not None:
            return f"{flag} is for a recording, not for --subscribe (the sheets' info says their lattice and link length)"
    if ns.method == "paper":
        return "--method paper with --subscribe: a worker estimates with auto, global or fused"
    if ns.sheets is not None and ns.worker is not None:
        from host.workers.distribute import Selection
        sel = Selection.of(ns.sheets, ns.worker)
        for s in sel.names:
            if not sel.in_share(s):
                return (f"--sheets {s} is not in --worker {ns.worker[0]}/{ns.worker[1]}'s share (CRC-32 of the name "
                        f"modulo {ns.worker[1]} is not {ns.worker[0]}): name it to that worker, or drop --worker")
    return None


def open_session(endpoint, config_file: str | None = None):
    """The worker's or the view's Zenoh session (`host.publish.zenoh_session.open_session`): ValueError
    for a config that cannot be used, OSError (one line) when it cannot be opened."""
    from host.publish.zenoh_session import open_session as open_
    try:
        return open_(endpoint, config_file)
    except OSError as exc:
        raise OSError(f"{exc} (is zenohd running there?)" if endpoint else str(exc)) from None


def _ask_info(session, sheet: str, timeout_s: float) -> dict | None:
    """``capsheet/<sheet>/info``'s answer, JSON decoded, or None when nobody answered in time."""
    for reply in session.get(f"capsheet/{sheet}/info", timeout=timeout_s):
        ok = reply.ok
        if ok is None:
            continue
        from host.publish.zenoh_pub import MAX_INFO_BYTES, decode_info
        if len(ok.payload) > MAX_INFO_BYTES:
            continue
        try:
            return decode_info(bytes(ok.payload.to_bytes()))
        except ValueError:
            continue
    return None


def limit_malloc_arenas(n: int = 2) -> bool:
    """On glibc, at most ``n`` malloc arenas for the process (``mallopt(M_ARENA_MAX)``). Zenoh's receive
    threads each got an arena of their own, and each kept the megabytes of the payloads it had freed:
    a worker flooded with 800 payloads of 1 MiB peaked at 382 MB with its queue never above 12 MB,
    137 MB with two arenas. True when set (False elsewhere: other C libraries, or no ctypes)."""
    try:
        import ctypes
        libc = ctypes.CDLL(None)
        return bool(libc.mallopt(-8, int(n)))  # M_ARENA_MAX (malloc.h)
    except (OSError, AttributeError, ImportError):
        return False


def run_worker(args) -> int:
    import zenoh

    from host.publish.zenoh_session import describe
    from host.workers.distribute import Selection, SheetWork, latency_ms
    from host.publish.zenoh_pub import HEADER, MAX_PAYLOAD_BYTES, decode_snapshot

    import host.analysis.estimator  # noqa: F401 -- before the first snapshot, not during it

    limit_malloc_arenas()  # before Zenoh's threads start: freed payloads are reused, not kept per thread
    try:
        session = open_session(args.subscribe[1], getattr(args, "zenoh_config", None))
    except ValueError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_FAIL

    def on_term(signum, frame):  # noqa: ARG001 - signal handler signature
        raise KeyboardInterrupt
    try:
        signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not the main thread
        pass

    inbox: queue.SimpleQueue = queue.SimpleQueue()
    peak = [0]
    queued = {"bytes": 0, "peak_bytes": 0}  # bytes in the inbox (Zenoh's thread adds, the loop takes)
    queue_lock = threading.Lock()
    queue_full: dict[str, int] = {}  # sheet -> payloads dropped because the inbox held MAX_QUEUED_BYTES

    def on_sample(sample) -> None:  # Zenoh's thread: queue only (a payload too big is never copied)
        key, size = str(sample.key_expr), len(sample.payload)
        if size > MAX_PAYLOAD_BYTES:
            inbox.put((key, size))  # counted as a bad payload by the loop
            return
        with queue_lock:
            if queued["bytes"] + size > MAX_QUEUED_BYTES:
                sheet = key.split("/")[1]
                queue_full[sheet] = queue_full.get(sheet, 0) + 1
                return
            queued["bytes"] += size
            queued["peak_bytes"] = max(queued["peak_bytes"], queued["bytes"])
        inbox.put((key, bytes(sample.payload.to_bytes())))

    def take(block: bool):
        """The next ``(sheet, payload or its size when refused unread)``; queue.Empty when none."""
        key, payload = inbox.get(timeout=0.05) if block else inbox.get_nowait()
        if isinstance(payload, bytes):
            with queue_lock:
                queued["bytes"] -= len(payload)
        return key.split("/")[1], payload

    period = 1.0 if args.uncertainty else None
    works: dict[str, SheetWork] = {}
    pending: dict[str, deque] = {}  # sheet -> payloads waiting for its info, oldest first
    pending_bytes: dict[str, int] = {}
    dropped_pending: dict[str, int] = {}  # sheet -> payloads dropped while waiting (MAX_PENDING_*)
    bad_pending: dict[str, list] = {}  # sheet -> [count, last reason]: refused while waiting for its info
    unknown_dropped = [0, set()]  # payloads of sheets beyond MAX_PENDING_SHEETS, and those sheets
    asked: dict[str, float] = {}
    ignored: set[str] = set()  # other workers' sheets (--worker)
    pubs: dict = {}
    def publish(sheet: str, out: bytes) -> None:
        pub = pubs.get(sheet)
        if pub is None:
            pub = pubs[sheet] = session.declare_publisher(
                f"capsheet/{sheet}/estimate", congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE)
        wall = HEADER.unpack_from(out)[-1]
        pub.put(out)
        works[sheet].latencies.append(time.time() - wall)

    def handle(sheet: str, payload) -> None:
        w = works[sheet]
        if not isinstance(payload, bytes):  # refused unread in Zenoh's thread: its size
            w.bad_payloads += 1
            w.last_bad = f"a payload of {payload} bytes, more than the largest sheet's {MAX_PAYLOAD_BYTES}"
            return
        out = w.work(payload, time.monotonic())
        if out is not None:
            publish(sheet, out)

    def hold(sheet: str, payload) -> None:
        """Keep a snapshot of a sheet whose info has not answered yet, if it is one (checked now)
        and the byte budgets allow."""
        try:
            if not isinstance(payload, bytes):
                raise ValueError(f"a payload of {payload} bytes, more than the largest sheet's {MAX_PAYLOAD_BYTES}")
            decode_snapshot(payload)
        except ValueError as exc:
            b = bad_pending.setdefault(sheet, [0, ""])
            b[0], b[1] = b[0] + 1, str(exc)
            return
        if sheet not in pending and len(pending) >= MAX_PENDING_SHEETS:
            unknown_dropped[0] += 1
            unknown_dropped[1].add(sheet)
            return
        p = pending.setdefault(sheet, deque())
        total = sum(pending_bytes.values())
        if total + len(payload) > MAX_PENDING_TOTAL_BYTES and not p:
            dropped_pending[sheet] = dropped_pending.get(sheet, 0) + 1
            return
        p.append(payload)
        pending_bytes[sheet] = pending_bytes.get(sheet, 0) + len(payload)
        while p and (pending_bytes[sheet] > MAX_PENDING_BYTES or sum(pending_bytes.values()) > MAX_PENDING_TOTAL_BYTES):
            pending_bytes[sheet] -= len(p.popleft())
            dropped_pending[sheet] = dropped_pending.get(sheet, 0) + 1

    code = EXIT_OK
    started = False
    t0 = time.monotonic()
    cpu0 = time.process_time()
    first_at = last_at = None
    interrupted = False
    subs: list = []
    sel = Selection.of(args.sheets, args.worker)
    try:
        subs += [session.declare_subscriber(k, on_sample) for k in sel.keys]
        if sel.names:  # each named sheet must answer: else it is unknown (a typo, a host not running)
            end = time.monotonic() + args.wait
            missing = list(sel.names)
            while missing and time.monotonic() < end:
                for s in list(missing):
                    doc = _ask_info(session, s, min(2.0, max(0.1, end - time.monotonic())))
                    if doc is not None:
                        try:
                            w = SheetWork(s, uncertainty_period_s=period, method=args.method)
                            w.set_info(doc)
                        except ValueError as exc:
                            print(f"{PROG}: {exc}", file=sys.stderr)
                            return EXIT_FAIL
                        works[s] = w
                        missing.remove(s)
                if missing:
                    time.sleep(0.2)
            if missing:
                print(f"{PROG}: unknown sheet{'s' if len(missing) > 1 else ''} {', '.join(missing)}: no answer from "
                      f"{', '.join(f'capsheet/{s}/info' for s in missing)} within {args.wait:g} s (is "
                      f"`capsheet host --publish zenoh --sheet-name NAME` running on this Zenoh network?)",
                      file=sys.stderr)
                return EXIT_FAIL
        share = "" if args.worker is None else f", worker {args.worker[0]}/{args.worker[1]}"
        print(f"{PROG}: worker ready ({describe(args.subscribe[1], getattr(args, 'zenoh_config', None))}; "
              f"{'sheets ' + ', '.join(args.sheets) if args.sheets else 'every sheet'}{share})", file=sys.stderr,
              flush=True)
        end = None if args.duration is None else t0 + args.duration
        started = True

        while True:
            now = time.monotonic()
            if end is not None and now >= end:
                break
            if args.idle is not None and last_at is not None and now - last_at >= args.idle:
                break
            for s in [s for s in pending if now - asked.get(s, -1e9) >= INFO_RETRY_S]:  # sheets without info yet
                asked[s] = now
                doc = _ask_info(session, s, 1.0)
                if doc is not None:
                    w = SheetWork(s, uncertainty_period_s=period, method=args.method)
                    try:
                        w.set_info(doc)
                    except ValueError as exc:
                        print(f"{PROG}: {exc}", file=sys.stderr)
                        continue
                    works[s] = w
                    pending_bytes.pop(s, None)
                    for payload in pending.pop(s):
                        handle(s, payload)
            try:
                sheet, payload = take(True)
            except queue.Empty:
                continue
            peak[0] = max(peak[0], inbox.qsize() + 1)
            last_at = time.monotonic()
            first_at = first_at or last_at
            if sheet in ignored:
                continue
            if sheet not in works:
                if not sel.takes(sheet):
                    ignored.add(sheet)
                    continue
                hold(sheet, payload)
                continue
            handle(sheet, payload)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        try:
            for sub in subs:
                sub.undeclare()
            # what had come before the end is still estimated: none of it is dropped
            while started:
                try:
                    sheet, payload = take(False)
                except queue.Empty:
                    break
                if sheet in works:
                    handle(sheet, payload)
                elif sheet not in ignored and sel.takes(sheet):
                    hold(sheet, payload)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            for pub in pubs.values():
                pub.undeclare()
            session.close()
    wall_s = time.monotonic() - t0
    cpu_s = time.process_time() - cpu0
    sheets = [w.summary() for _, w in sorted(works.items())]
    for s in sorted(set(pending) | set(bad_pending)):  # snapshots came, the sheet's info never did
        n_ok, n_bad = len(pending.get(s, ())) + dropped_pending.get(s, 0), bad_pending.get(s, [0])[0]
        sheets.append({"sheet": s, "info": False, "received": n_ok + n_bad, "estimated": 0,
                       "not_estimated": n_ok, "bad_payloads": n_bad,
                       "last_bad": bad_pending.get(s, [0, ""])[1], "dropped_waiting": dropped_pending.get(s, 0),
                       "lost": 0, "gaps": 0, "latency_ms": latency_ms([])})
    for d in sheets:
        d["dropped_queue_full"] = queue_full.get(d["sheet"], 0)
    lines = []
    for d in sheets:
        if not d["info"]:
            lines.append(f"{PROG}: sheet {d['sheet']}: {d['received']} snapshots received, none estimated: "
                         f"capsheet/{d['sheet']}/info never answered"
                         + (f"; {d['dropped_waiting']} dropped while waiting (more than "
                            f"{MAX_PENDING_BYTES >> 20} MB held)" if d["dropped_waiting"] else "")
                         + (f"; {d['bad_payloads']} bad payloads refused (the last: {d['last_bad']})"
                            if d["bad_payloads"] else ""))
            code = EXIT_FAIL
            continue
        lat = d["latency_ms"]
        extra = "".join(f", {d[k]} {k.replace('_', ' ')} dropped" for k in ("duplicates", "old", "bad_payloads")
                        if d[k]) + (f" (the last: {d['last_bad']})" if d["bad_payloads"] else "")
        if d["dropped_queue_full"]:
            extra += f", {d['dropped_queue_full']} dropped with the worker's queue full ({MAX_QUEUED_BYTES >> 20} MB)"
        lines.append(f"{PROG}: sheet {d['sheet']}: received {d['received']}"
                     + (f" (counters {d['first_counter']}..{d['last_counter']})" if d["received"] else "")
                     + f", estimated {d['estimated']}"
                     + (f" ({', '.join(f'{n} {m}' for m, n in sorted(d['methods'].items()))})" if d["methods"] else "")
                     + f", not estimated {d['not_estimated']}"
                     + "".join(f" ({n}: {why})" for why, n in d["not_estimated_reasons"].items())
                     + f", lost {d['lost']} in {d['gaps']} gap{'s' if d['gaps'] != 1 else ''}{extra}"
                     + (f", counting restarted {d['restarts']} time(s) (the host started again)" if d["restarts"] else "")
                     + (f"; SYNC -> published estimate p50 {lat['p50']} ms, p99 {lat['p99']} ms" if lat["n"] else ""))
        if d["lost"] or d["bad_payloads"] or d["duplicates"] or d["old"] or d["dropped_queue_full"]:
            code = EXIT_FAIL
    if not any(d["received"] for d in sheets):
        lines.append(f"{PROG}: received no snapshot"
                     + (f" from {', '.join(args.sheets)}" if args.sheets else "")
                     + " (is a host publishing with --publish zenoh on this Zenoh network?)")
        code = EXIT_FAIL
    if unknown_dropped[0]:
        lines.append(f"{PROG}: {unknown_dropped[0]} snapshots of {len(unknown_dropped[1])} more sheets dropped: "
                     f"{MAX_PENDING_SHEETS} sheets were already waiting for their info")
        code = EXIT_FAIL
    if ignored:
        lines.append(f"{PROG}: left {len(ignored)} sheet(s) not selected (--sheets, --worker): "
                     f"{', '.join(sorted(ignored))}")
    lines.append(f"{PROG}: {sum(d['received'] for d in sheets)} snapshots, "
                 f"{sum(d['estimated'] for d in sheets)} estimated in {wall_s:.1f} s, {cpu_s:.2f} s of CPU, "
                 f"queue peak {peak[0]} ({queued['peak_bytes'] / 1e6:.1f} MB)" + (" (interrupted)" if interrupted else ""))
    if not args.quiet or code != EXIT_OK:
        for line in lines:
            print(line, file=sys.stderr)
    if args.json:
        print(json.dumps({"sheets": sheets, "ignored": sorted(ignored), "wall_s": round(wall_s, 3),
                          "cpu_s": round(cpu_s, 3), "queue_peak": peak[0], "queue_peak_bytes": queued["peak_bytes"],
                          "interrupted": interrupted,
                          "exit": code}, indent=1))
    return code
