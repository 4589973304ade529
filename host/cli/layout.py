"""``capsheet layout``: learn which chip is on which link from the sheet itself, or check a layout.

``capsheet layout learn --port P --lattice RxC --out sheet.csv`` guides you through four poses —
flat, a ramp, a hump across the rows, a hump across the columns — each prompted, each taken when
the readings have changed and then settled (`host.analysis.layout.PoseDetector`); from what the
chips read in them it decides every chip's link (`host.analysis.layout.learn_layout`), checks the
result with the lattice's loop closure and writes the layout (a temporary file renamed into place:
Ctrl-C leaves nothing half-written).

``capsheet layout check --port P --layout sheet.csv`` runs the same poses and holds the layout to
them: chips swapped or on the wrong link ("links 17 and 18 look swapped"), chips that did not
answer, unknown chips, and a lone new chip in place of a dead one (it takes the dead one's link);
``--out fixed.csv`` writes the layout with those fixed. ``--ids-only`` skips the poses: it checks
which chips answer and fixes a lone replacement.

Exit status: 0 the layout is learned and its loops close / the layout fits (or every finding was
fixed into --out); 1 it does not (the learned layout is still written, with what is wrong said);
2 bad values; 130 interrupted (nothing written).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["register", "collect_poses", "write_layout_atomic"]

#: the SYNC rate the poses are read at: a pose is held for seconds, 50 readings a second is plenty
DEFAULT_RATE_HZ = 50.0


def register(sub) -> None:
    from host.cli import argtypes as T
    from host.cli.timing_args import add_timing_args
    from host.cli.transport_args import add_transport_args

    p = sub.add_parser("layout", help="learn which chip is on which link from the sheet itself, or check a layout",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    lsub = p.add_subparsers(dest="layout_command", metavar="ACTION")

    def common(q) -> None:
        add_transport_args(q, title="the sheet's port", several_buses=True)
        q.add_argument("--rate", type=T.rate, default=DEFAULT_RATE_HZ,
                       help=f"SYNC rate while the poses are read, Hz (default {DEFAULT_RATE_HZ:g})")
        q.add_argument("--settle-s", type=T.bounded_float(0.3, 30.0), default=1.0, metavar="S",
                       help="how long a pose must be held still before it is taken, seconds (default 1)")
        q.add_argument("--settle-deg", type=T.bounded_float(0.1, 20.0), default=2.0, metavar="DEG",
                       help="how far a chip may waver while still, degrees (default 2)")
        q.add_argument("--pose-timeout-s", type=T.bounded_float(1.0, 3600.0), default=300.0, metavar="S",
                       help="give up when a pose has not been taken after this long, seconds (default 300)")
        q.add_argument("--json", action="store_true", help="print the result as JSON alone on stdout")
        add_timing_args(q)  # --ack-timeout-ms --watchdog-ms

    learn = lsub.add_parser("learn", help="learn the layout from four poses of the sheet",
                            description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common(learn)
    learn.add_argument("--lattice", type=T.lattice, required=True, help="joints, ROWSxCOLS (e.g. 8x8)")
    learn.add_argument("--out", type=T.output_file(".csv", ".json", what="a layout file"), required=True,
                       help="the layout file to write (CSV, or JSON if .json)")
    T.add_overwrite_arg(learn, "the --out file")
    learn.set_defaults(func=cmd_learn)

    check = lsub.add_parser("check", help="find swapped, missing or replaced chips in a layout",
                            description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common(check)
    check.add_argument("--layout", required=True, type=T.existing_file(".csv", ".json", what="a layout file"),
                       help="the layout to check (CSV or JSON)")
    check.add_argument("--lattice", type=T.lattice, default=None,
                       help="joints, ROWSxCOLS (default: the layout file's, a JSON layout names it)")
    check.add_argument("--out", type=T.output_file(".csv", ".json", what="a layout file"), default=None,
                       help="write the layout with what was found fixed")
    check.add_argument("--ids-only", action="store_true",
                       help="no poses: check which chips answer, fix a lone replacement")
    T.add_overwrite_arg(check, "the --out file")
    check.set_defaults(func=cmd_check)
    p.set_defaults(func=lambda args: (p.print_help(sys.stderr), 2)[1])


# ---------------------------------------------------------------------------------------------
# the session: bring the sheet up without a layout, read the poses
# ---------------------------------------------------------------------------------------------

def _say(args, text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def open_host(transports, lattice, rate_hz: float, **timing):
    """A `Host` on ``transports`` that assigns every chip some link (a layout is what is being
    learned: the positions say nothing; the learner sees uids and readings only). ``timing``: the
    ``--ack-timeout-ms`` / ``--watchdog-ms`` keywords (`host.cli.timing_args.timing_kwargs`)."""
    import logging
    from host.session.core import Host
    # auto-assign says "positions are arbitrary": known here, the learner uses uids, not positions
    logging.getLogger("capsheet.host").addFilter(lambda rec: "auto-assign" not in rec.getMessage())
    return Host(transports, lattice, layout=None, rate_hz=rate_hz, **timing)


def collect_poses(host, steps, *, settle_s: float = 1.0, settle_deg: float = 2.0, timeout_s: float = 300.0,
                  say=print) -> dict:
    """Prompt each of ``steps`` (name, prompt) in turn and take the next settled pose that passes
    `judge_pose` for it; returns ``{name: {uid: mean reading}}``. The host streams (brought up).
    Raises TimeoutError (a step not taken within ``timeout_s``)."""
    import numpy as np
    from host.analysis.layout import PoseDetector, judge_pose

    uid_of = {rec.link: rec.uid for rec in host.assigned_chips() if rec.link is not None}
    n = host.lattice.n_links
    link_uid = np.zeros(n, dtype=np.uint64)
    known = np.zeros(n, dtype=bool)
    for k, u in uid_of.items():
        link_uid[k], known[k] = u, True
    det = PoseDetector(settle_s=settle_s, settle_deg=settle_deg)
    out: dict = {}
    for k, (name, prompt) in enumerate(steps):
        say(f"step {k + 1}/{len(steps)} ({name}): {prompt}")
        t_end = time.monotonic() + timeout_s
        while True:
            if time.monotonic() > t_end:
                raise TimeoutError(f"step {k + 1} ({name}) not taken within {timeout_s:g} s: no settled pose "
                                   f"that is one (poses seen: {det.poses_taken})")
            snap = host.get(0.5)
            if snap is None:
                continue
            sel = snap.valid & known
            det.add_many(link_uid[sel], snap.readings[sel], snap.timestamp)
            pose = det.poll(snap.timestamp)
            if pose is None:
                continue
            readings = pose.readings()
            why = judge_pose(name, readings)
            if why is None:
                out[name] = readings
                say(f"  took {name}: {len(readings)} chips, held {pose.end_s - pose.start_s:.1f} s")
                break
            say(f"  a pose settled but it is {why}; waiting for {name}")
    return out


def write_layout_atomic(path, links: dict, rows: int, cols: int) -> Path:
    """Write the layout to a temporary file beside ``path`` and rename it into place: an
    interrupted run leaves the old file (or none), never half a layout."""
    from protocol.layout import format_layout
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent if str(path.parent) else ".")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(format_layout(links, str(path), rows, cols))
        os.replace(tmp, path)
        tmp = None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
    return path


def _run_session(args, lattice, steps):
    """Open the ports, bring the sheet up, read ``steps``; returns (poses, chips heard)."""
    from host.cli.transport_args import open_transports
    from host.session.errors import SessionError
    from host.transport.ports import TransportError

    prog = f"capsheet layout {args.layout_command}"
    try:
        transports = open_transports(args, prog=prog)
    except TransportError as exc:
        raise SystemExit(_fail(prog, f"cannot open the port: {exc}"))
    from host.cli.timing_args import timing_kwargs
    host = open_host(transports, lattice, args.rate, **timing_kwargs(args))
    try:
        with host:
            try:
                summary = host.bring_up()
            except SessionError as exc:
                raise SystemExit(_fail(prog, f"bring-up failed: {exc}"))
            heard = {rec.uid for rec in host.assigned_chips()}
            _say(args, f"{prog}: {summary['discovered']} chips answered ({lattice.n_links} links on "
                       f"{lattice.rows}x{lattice.cols})")
            if not steps:
                return {}, heard
            try:
                poses = collect_poses(host, steps, settle_s=args.settle_s, settle_deg=args.settle_deg,
                                      timeout_s=args.pose_timeout_s, say=lambda s: _say(args, s))
            except TimeoutError as exc:
                raise SystemExit(_fail(prog, str(exc), code=1))
            host.stop()
            return poses, heard
    finally:
        for t in transports:
            try:
                t.close()
            except Exception:  # noqa: BLE001 - closing what the host may have closed already
                pass


def _fail(prog: str, msg: str, code: int = 1) -> int:
    print(f"{prog}: {msg}", file=sys.stderr)
    return code


def _print_result(args, result: dict, lines: list[str]) -> None:
    out = sys.stderr if args.json else sys.stdout
    for ln in lines:
        print(ln, file=out)
    if args.json:
        print(json.dumps(result, indent=1))


# ---------------------------------------------------------------------------------------------
# learn
# ---------------------------------------------------------------------------------------------

def learn_from_poses(lattice, poses: dict) -> tuple[dict, list[str], bool]:
    """(result dict, lines to print, loops close) of learning from ``poses``."""
    from host.analysis.layout import learn_layout
    res = learn_layout(lattice, poses)
    lines = [f"placed {len(res.layout)} chips on {lattice.n_links} links; loop closure: largest unit residual "
             f"{res.max_residual:.3g} (limit {res.limit:.3g})" if res.max_residual is not None else
             f"placed {len(res.layout)} chips on {lattice.n_links} links"]
    for k in res.missing_links:
        lines.append(f"link {k}: no chip placed (a dead chip there, or one chip short)")
    for u, why in res.unplaced.items():
        lines.append(f"chip 0x{u:016X} not placed: {why}")
    for k in res.reversed_links:
        lines.append(f"link {k}: its chip reads turned half round (x and y reversed): remount it")
    bad = res.bad_units
    if bad:
        lines.append(f"{len(bad)} units do not close: " + ", ".join(f"({i},{j})" for i, j in bad[:6])
                     + (" ..." if len(bad) > 6 else ""))
    lines.extend(res.notes)
    ok = res.loop_closure_ok and not res.reversed_links
    result = {"lattice": f"{lattice.rows}x{lattice.cols}", "links": lattice.n_links, "placed": len(res.layout),
              "missing_links": res.missing_links, "unplaced": {f"0x{u:016X}": w for u, w in res.unplaced.items()},
              "reversed_links": res.reversed_links, "max_unit_residual": res.max_residual, "residual_limit": res.limit,
              "bad_units": [list(u) for u in bad], "loop_closure_ok": res.loop_closure_ok, "notes": res.notes,
              "layout": {f"0x{u:016X}": k for u, k in sorted(res.layout.items(), key=lambda kv: kv[1])}}
    return result, lines, ok


def cmd_learn(args) -> int:
    from host.analysis.layout import PROCEDURE, LayoutLearnError
    lat = args.lattice
    poses, _heard = _run_session(args, lat, PROCEDURE)
    try:
        result, lines, ok = learn_from_poses(lat, poses)
    except LayoutLearnError as exc:
        return _fail("capsheet layout learn", str(exc))
    links = {int(u, 16): k for u, k in result["layout"].items()}
    write_layout_atomic(args.out, links, lat.rows, lat.cols)
    result["out"] = str(args.out)
    lines.append(f"wrote {args.out}" + ("" if ok else " (check it: the loops above do not close; chips with errors "
                                                      "of their own leave a few such units: calibrate them first, "
                                                      "capsheet calibrate --write-chips)"))
    _print_result(args, result, lines)
    return 0 if ok else 1


# ---------------------------------------------------------------------------------------------
# check
# ---------------------------------------------------------------------------------------------

def cmd_check(args) -> int:
    from host.analysis.layout import PROCEDURE, LayoutLearnError, check_layout
    from protocol.layout import LayoutError, load_layout
    prog = "capsheet layout check"
    try:
        doc = load_layout(args.layout)
    except LayoutError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    lat = args.lattice
    if lat is None:
        if doc.rows is None:
            print(f"{prog}: {args.layout} does not name its lattice: give --lattice ROWSxCOLS", file=sys.stderr)
            return 2
        from protocol.lattice import Lattice
        lat = Lattice(doc.rows, doc.cols)
    over = sorted(k for k in doc.links.values() if k >= lat.n_links)
    if over:
        print(f"{prog}: {args.layout} names link {over[0]}, outside {lat.rows}x{lat.cols} ({lat.n_links} links)",
              file=sys.stderr)
        return 2
    poses, heard = _run_session(args, lat, () if args.ids_only else PROCEDURE)
    if args.ids_only:
        poses = {"flat": {u: (0.0, 0.0, 1.0) for u in heard}}
    try:
        res = check_layout(lat, poses, doc.links)
    except LayoutLearnError as exc:
        return _fail(prog, str(exc))
    lines = list(res.findings) or ["the layout fits the sheet: every chip answered"
                                   + ("" if args.ids_only else " and every unit's loops close")]
    wrote = None
    if args.out and not res.ok:
        write_layout_atomic(args.out, res.fixed, lat.rows, lat.cols)
        wrote = str(args.out)
        lines.append(f"wrote {args.out} with {'every finding' if res.fixed_all else 'what could be'} fixed")
    import numpy as np
    result = {"lattice": f"{lat.rows}x{lat.cols}", "ok": res.ok, "findings": res.findings,
              "fixed_all": res.fixed_all, "out": wrote,
              "max_unit_residual": (None if res.unit_residual is None or not np.isfinite(res.unit_residual).any()
                                    else float(np.nanmax(res.unit_residual)))}
    _print_result(args, result, lines)
    return 0 if res.ok or (wrote and res.fixed_all) else 1
