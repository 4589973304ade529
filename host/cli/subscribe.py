"""``capsheet estimate --subscribe [zenoh[:ENDPOINT]]``: an estimate worker on Zenoh (issue 31, point 3).

The worker subscribes to the snapshots hosts publish (``capsheet host --publish zenoh``), asks each
sheet's ``capsheet/<sheet>/info`` queryable for its lattice and link length (a late joiner gets them
too), estimates every snapshot of its sheets in the order they came with the estimator the host
uses (`host.analysis.estimator.estimate`, warm-started from the sheet's previous estimate) and
publishes one estimate per snapshot under ``capsheet/<sheet>/estimate``. `host.workers.distribute` does the
per-sheet work without I/O; this module is the Zenoh session, the queue and the summary.

Zenoh's callbacks only queue the payloads (one FIFO for all sheets, unbounded, its peak reported):
a slow estimate never makes the network drop what the worker was sent, and each sheet's snapshots
stay in order. Estimates are put with congestion control BLOCK: a slow subscriber of the estimates
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
import time

__all__ = ["add_subscribe_args", "check_subscribe", "run_worker", "subscribe_arg", "open_session",
           "add_zenoh_config_arg", "zenoh_config_arg"]

PROG = "capsheet estimate"
EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2
#: how often a sheet whose info did not answer is asked again, s
INFO_RETRY_S = 1.0
#: snapshots kept for a sheet whose info has not answered yet; beyond, the oldest are dropped (counted)
MAX_PENDING = 100_000


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
        raise OSError(f"{exc} (is the router running there?)" if endpoint else str(exc)) from None


def _ask_info(session, sheet: str, timeout_s: float) -> dict | None:
    """``capsheet/<sheet>/info``'s answer, JSON decoded, or None when nobody answered in time."""
    for reply in session.get(f"capsheet/{sheet}/info", timeout=timeout_s):
        ok = reply.ok
        if ok is None:
            continue
        try:
            return json.loads(bytes(ok.payload.to_bytes()))
        except ValueError:
            continue
    return None


def run_worker(args) -> int:
    import zenoh

    from host.publish.zenoh_session import describe
    from host.workers.distribute import Selection, SheetWork, latency_ms
    from host.publish.zenoh_pub import HEADER

    import host.analysis.estimator  # noqa: F401 -- before the first snapshot, not during it

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

    def on_sample(sample) -> None:  # Zenoh's thread: queue only
        inbox.put((str(sample.key_expr), bytes(sample.payload.to_bytes())))

    period = 1.0 if args.uncertainty else None
    works: dict[str, SheetWork] = {}
    pending: dict[str, list] = {}  # sheet -> payloads waiting for its info
    dropped_pending: dict[str, int] = {}
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

    def handle(sheet: str, payload: bytes) -> None:
        w = works[sheet]
        out = w.work(payload, time.monotonic())
        if out is not None:
            publish(sheet, out)

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
                    for payload in pending.pop(s):
                        handle(s, payload)
            try:
                key, payload = inbox.get(timeout=0.05)
            except queue.Empty:
                continue
            peak[0] = max(peak[0], inbox.qsize() + 1)
            last_at = time.monotonic()
            first_at = first_at or last_at
            sheet = key.split("/")[1]
            if sheet in ignored:
                continue
            if sheet not in works:
                if not sel.takes(sheet):
                    ignored.add(sheet)
                    continue
                p = pending.setdefault(sheet, [])
                p.append(payload)
                if len(p) > MAX_PENDING:
                    p.pop(0)
                    dropped_pending[sheet] = dropped_pending.get(sheet, 0) + 1
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
                    key, payload = inbox.get_nowait()
                except queue.Empty:
                    break
                sheet = key.split("/")[1]
                if sheet in works:
                    out = works[sheet].work(payload, time.monotonic())
                    if out is not None:
                        publish(sheet, out)
                elif sheet not in ignored and sel.takes(sheet):
                    pending.setdefault(sheet, []).append(payload)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            for pub in pubs.values():
                pub.undeclare()
            session.close()
    wall_s = time.monotonic() - t0
    cpu_s = time.process_time() - cpu0
    sheets = [w.summary() for _, w in sorted(works.items())]
    for s, p in sorted(pending.items()):  # snapshots came, the sheet's info never did
        sheets.append({"sheet": s, "info": False, "received": len(p) + dropped_pending.get(s, 0), "estimated": 0,
                       "not_estimated": len(p) + dropped_pending.get(s, 0), "lost": 0, "gaps": 0,
                       "latency_ms": latency_ms([])})
    lines = []
    for d in sheets:
        if not d["info"]:
            lines.append(f"{PROG}: sheet {d['sheet']}: {d['received']} snapshots received, none estimated: "
                         f"capsheet/{d['sheet']}/info never answered")
            code = EXIT_FAIL
            continue
        lat = d["latency_ms"]
        extra = "".join(f", {d[k]} {k.replace('_', ' ')} dropped" for k in ("duplicates", "old", "bad_payloads")
                        if d[k])
        lines.append(f"{PROG}: sheet {d['sheet']}: received {d['received']}"
                     + (f" (counters {d['first_counter']}..{d['last_counter']})" if d["received"] else "")
                     + f", estimated {d['estimated']}"
                     + (f" ({', '.join(f'{n} {m}' for m, n in sorted(d['methods'].items()))})" if d["methods"] else "")
                     + f", not estimated {d['not_estimated']}"
                     + "".join(f" ({n}: {why})" for why, n in d["not_estimated_reasons"].items())
                     + f", lost {d['lost']} in {d['gaps']} gap{'s' if d['gaps'] != 1 else ''}{extra}"
                     + (f", counting restarted {d['restarts']} time(s) (the host started again)" if d["restarts"] else "")
                     + (f"; SYNC -> published estimate p50 {lat['p50']} ms, p99 {lat['p99']} ms" if lat["n"] else ""))
        if d["lost"] or d["bad_payloads"] or d["duplicates"] or d["old"]:
            code = EXIT_FAIL
    if not any(d["received"] for d in sheets):
        lines.append(f"{PROG}: received no snapshot"
                     + (f" from {', '.join(args.sheets)}" if args.sheets else "")
                     + " (is a host publishing with --publish zenoh on this Zenoh network?)")
        code = EXIT_FAIL
    if ignored:
        lines.append(f"{PROG}: left {len(ignored)} sheet(s) not selected (--sheets, --worker): "
                     f"{', '.join(sorted(ignored))}")
    lines.append(f"{PROG}: {sum(d['received'] for d in sheets)} snapshots, "
                 f"{sum(d['estimated'] for d in sheets)} estimated in {wall_s:.1f} s, {cpu_s:.2f} s of CPU, "
                 f"queue peak {peak[0]}" + (" (interrupted)" if interrupted else ""))
    if not args.quiet or code != EXIT_OK:
        for line in lines:
            print(line, file=sys.stderr)
    if args.json:
        print(json.dumps({"sheets": sheets, "ignored": sorted(ignored), "wall_s": round(wall_s, 3),
                          "cpu_s": round(cpu_s, 3), "queue_peak": peak[0], "interrupted": interrupted,
                          "exit": code}, indent=1))
    return code
