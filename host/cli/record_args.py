"""The recording options the commands that run a sheet share (``capsheet host``, ``demo``,
``tactile``): ``--record FILE.mcap``, ``--live [PORT]``, ``--publish zenoh|ros2[:ENDPOINT]`` (with
``--sheet-name``), ``--record-ros2 FILE.mcap`` and, on CAN, ``--can-log FILE``.

One definition, so the three commands spell and explain them alike; `SessionOutputs` does the
wiring (raw taps, SYNC taps, session facts, live estimates) so each command adds one block.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections import deque
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from host.cli.argtypes import OptionGroup

__all__ = ["add_record_args", "SessionOutputs", "CAN_LOG_SUFFIXES"]

#: the python-can log formats ``--can-log`` writes (and ``capsheet replay`` reads)
CAN_LOG_SUFFIXES = (".log", ".asc", ".blf")


def add_record_args(parser: argparse.ArgumentParser, *, can_log: bool = False,
                    link_length: bool = False, estimate_process: bool = False) -> OptionGroup:
    """Add ``--record``, ``--live``, ``--live-rate``, ``--overwrite`` (and ``--can-log``,
    ``--link-length``). Every value is checked by `host.cli.argtypes`: an existing recording is
    replaced only with ``--overwrite``."""
    from host.cli import argtypes as T

    g = parser.add_argument_group("recording and live view (docs/recording.md)")
    g.add_argument("--record", metavar="FILE.mcap", type=T.output_file(".mcap", what="an MCAP recording"),
                   help="record raw input, snapshots, estimates and the 3D scene to an MCAP file "
                        "(Foxglove opens it; host.record.read loads it); an existing file needs --overwrite")
    g.add_argument("--live", metavar="PORT", type=T.tcp_port, nargs="?", const=8765, default=None,
                   help="serve the live 3D view over the Foxglove WebSocket protocol (subprotocols "
                        "foxglove.sdk.v1 and foxglove.websocket.v1) on localhost (default port 8765; "
                        "open ws://localhost:8765 in Foxglove or Lichtblick)")
    add_live_server_args(g, parser)
    g.add_argument("--live-rate", type=T.bounded_float(0.0, 1000.0, lo_open=True, unit="per s"), default=20.0,
                   help="estimates per second for the live view and the recording (default 20)")
    g.add_argument("--split-size", metavar="MB", type=T.bounded_float(0.0, 1e7, lo_open=True, unit="MB"),
                   help="start a new file of the recording once one holds this many MB: FILE_0000.mcap, "
                        "FILE_0001.mcap, ..., each readable alone (replay and estimate take the set)")
    g.add_argument("--split-duration", metavar="S", type=T.duration,
                   help="start a new file of the recording every S seconds (as --split-size)")
    g.add_argument("--min-free", metavar="MB", type=T.bounded_float(0.0, 1e9, unit="MB"), default=DEFAULT_MIN_FREE_MB,
                   help="free disk space the recording leaves: checked at the start (refused below it) and "
                        f"every second, where the recording stops cleanly, its file readable (default "
                        f"{DEFAULT_MIN_FREE_MB:g} MB; 0: until the disk is full)")
    g.add_argument("--record-process", action=argparse.BooleanOptionalAction, default=None,
                   help="write the recording in a process of its own (the same file; the compression then "
                        "holds no lock this process's receive and SYNC threads need; not with --live, whose view "
                        "shares this process's writer). Default: for a sheet of more than 2,048 links")
    T.add_overwrite_arg(g, "recordings (--record" + (", --can-log)" if can_log else ")"))
    if hasattr(parser, "add_check"):
        parser.add_check(check_record_process)
    g.add_argument("--publish", metavar="zenoh|ros2[:ENDPOINT]", type=_publish_arg, default=None,
                   help="zenoh: publish snapshots, estimates, health and (queryable) layout and calibration to "
                        "Zenoh under capsheet/<sheet>/...; ros2: the same as ROS 2 messages laid out as rmw_zenoh "
                        "does (/capsheet/<sheet>/snapshot, joints, surface, contacts, /diagnostics, and with gyroscopes "
                        "link_<k>/imu/data and imu/mag per link; ROS_DOMAIN_ID), "
                        "readable by a ROS 2 install with rmw_zenoh (docs/distribution.md). Peer mode on loopback "
                        "only (127.0.0.1, no multicast scouting; the machine's sessions meet at tcp/127.0.0.1:7447), "
                        "or connected to ENDPOINT (a Zenoh locator, e.g. tcp/10.0.0.2:7447), or --zenoh-config")
    from host.cli.subscribe import add_zenoh_config_arg
    add_zenoh_config_arg(g)
    g.add_argument("--no-publish-estimates", action="store_true",
                   help="--publish zenoh: publish snapshots, health and info but no estimates, and make none for "
                        "it: capsheet/<sheet>/estimate is left to estimate workers (capsheet estimate --subscribe), "
                        "this host's CPU to its sheet")
    g.add_argument("--sheet-name", metavar="NAME", type=_sheet_name, default="sheet",
                   help="the sheet's name in the published key expressions and ROS 2 topics (default 'sheet'; "
                        "for ros2 a ROS name: letters, digits, _)")
    g.add_argument("--record-ros2", metavar="FILE.mcap", type=T.output_file(".mcap", what="a ROS 2 MCAP recording"),
                   help="also record the ROS 2 messages of --publish ros2 (CDR) to a ROS 2-profile MCAP "
                        "(ros2 bag, rosbags and Foxglove read it); an existing file needs --overwrite")
    if hasattr(parser, "add_check"):  # a `host.cli.argtypes.CliParser`
        parser.add_check(_check_ros2)
        parser.add_check(_check_no_estimates)
    if can_log:
        g.add_argument("--can-log", metavar="FILE", type=T.output_file(*CAN_LOG_SUFFIXES, what="a CAN log"),
                       help="also log every CAN frame, received (Rx) and sent by this host (Tx), with python-can's "
                            "logger (.log candump, .asc, .blf; cantools and capsheet replay read it)")
    if estimate_process:
        g.add_argument("--estimate-process", action=argparse.BooleanOptionalAction, default=None,
                       help="make the estimates of --record/--live/--publish in a process of their own "
                            "(host/workers/estimate_worker.py): the receive threads keep the interpreter to "
                            "themselves and every snapshot up to --live-rate is estimated, in order; "
                            "accelerometer sheets only. Default: chosen for the sheet, on for a big sheet at "
                            "a high rate (as --reader-processes; docs/host.md)")
    if link_length:
        g.add_argument("--link-length", type=T.link_length, default=0.01,
                       help="L, metres, for estimates and the 3D view (default 0.01)")
    return g


def add_live_server_args(g, parser) -> None:
    """The live view server's limits and TLS (``--live``, ``capsheet view``) in group ``g`` of
    ``parser``: `live_options` reads them."""
    from host.cli import argtypes as T
    from host.publish.live import MAX_CLIENTS
    g.add_argument("--live-max-clients", metavar="N", type=T.int_range(1, 1024), default=MAX_CLIENTS,
                   help=f"live view: clients served at once; more are answered HTTP 503 (default {MAX_CLIENTS})")
    g.add_argument("--live-origin", metavar="ORIGIN", action="append", default=None,
                   help="live view: serve browsers from this origin only (e.g. https://app.foxglove.dev; repeat "
                        "for several); a page from any other origin is answered HTTP 403, so it cannot read the "
                        "sheet through your browser. Clients that send no Origin (not browsers) are served. "
                        "Default: any origin")
    g.add_argument("--live-tls-cert", metavar="CERT.pem", type=T.existing_file(what="a PEM certificate"),
                   default=None, help="live view: serve wss:// with this certificate (chain), with --live-tls-key")
    g.add_argument("--live-tls-key", metavar="KEY.pem", type=T.existing_file(what="a PEM private key"),
                   default=None, help="live view: the certificate's private key (with --live-tls-cert)")
    if hasattr(parser, "add_check"):  # a `host.cli.argtypes.CliParser`
        parser.add_check(check_live_server_args)


def check_record_process(ns) -> str | None:
    """``--record-process`` asked for where it cannot write: a live view's recording (the view shares
    this process's writer) or no recording at all — refused, never silently written the other way."""
    if not getattr(ns, "record_process", None):
        return None
    if not getattr(ns, "record", None):
        return "--record-process writes a --record file: give --record FILE"
    if getattr(ns, "live", None) is not None:
        return "--record-process with --live: the live view shares this process's writer (drop one of them)"
    return None


def check_live_server_args(ns) -> str | None:
    """Usage errors of the live view's TLS: both files or neither, and they must load."""
    cert, key = getattr(ns, "live_tls_cert", None), getattr(ns, "live_tls_key", None)
    if cert is None and key is None:
        return None
    from host.publish.live import tls_context
    try:
        tls_context(cert, key)
    except ValueError as exc:
        return f"--live-tls-cert/--live-tls-key: {exc}"
    return None


def live_options(args) -> dict:
    """`host.publish.live.LiveServer`'s keyword arguments from `add_live_server_args`' options."""
    from host.publish.live import MAX_CLIENTS
    return {"max_clients": getattr(args, "live_max_clients", MAX_CLIENTS),
            "allowed_origins": getattr(args, "live_origin", None),
            "tls_cert": getattr(args, "live_tls_cert", None), "tls_key": getattr(args, "live_tls_key", None)}


def where_zenoh(endpoint, args) -> str:
    """Where ``--publish`` talks, for messages (`host.publish.zenoh_session.describe`)."""
    from host.publish.zenoh_session import describe
    return describe(endpoint, getattr(args, "zenoh_config", None))


def _publish_arg(value: str):
    from host.publish.zenoh_pub import parse_publish
    try:
        return parse_publish(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _check_no_estimates(ns) -> str | None:
    publish = getattr(ns, "publish", None)
    if getattr(ns, "no_publish_estimates", False) and (publish is None or publish[0] != "zenoh"):
        return "--no-publish-estimates is for --publish zenoh (estimate workers make the estimates)"
    return None


def _check_ros2(ns) -> str | None:
    """--publish ros2 / --record-ros2 need a sheet name that is a ROS name and a valid ROS_DOMAIN_ID."""
    publish = getattr(ns, "publish", None)
    if not ((publish is not None and publish[0] == "ros2") or getattr(ns, "record_ros2", None)):
        return None
    from host.publish.ros2 import ROS_NAME, domain_id
    sheet = getattr(ns, "sheet_name", "sheet")
    if not ROS_NAME.match(sheet):
        return (f"--sheet-name {sheet!r} is not a ROS 2 name (--publish ros2, --record-ros2): 1-64 of "
                f"A-Z a-z 0-9 _, starting with a letter")
    try:
        domain_id()
    except ValueError as exc:
        return f"{exc} (--publish ros2, --record-ros2)"
    return None


def _sheet_name(value: str) -> str:
    from host.publish.zenoh_pub import SHEET_NAME
    if not SHEET_NAME.match(value):
        raise argparse.ArgumentTypeError(f"bad sheet name {value!r}: 1-64 of A-Z a-z 0-9 _ . - (one key chunk)")
    return value


def contact_dicts(contacts) -> list[dict]:
    """`host.analysis.tactile.Contact` s as the plain dicts a recording stores."""
    return [{"id": int(c.id), "index": [float(v) for v in c.index], "position": [float(v) for v in c.position],
             "force_n": float(c.force_n), "depth_m": float(c.depth_m), "area_m2": float(c.area_m2),
             "radius_m": float(np.max(c.axes_m))} for c in contacts]


#: --min-free default, MB: 20 minutes of a 14x14 145 Hz recording (docs/recording.md)
DEFAULT_MIN_FREE_MB = 500.0

#: a live session records an estimate's sampled uncertainty (yaw_std, joint_std: ~100 ms of CPU at
#: 14x14) at most this often; the other estimates carry joints only
UNCERTAINTY_PERIOD_S = 1.0
#: --estimate-process: --live-rate holds on average over this long (or one period), not snapshot by snapshot
ESTIMATE_CREDIT_S = 0.1
#: --estimate-process: snapshots due an estimate wait in order while the estimator process is full,
#: this many seconds of them at most, by their own times (their SYNC); the oldest is given up past
#: it. A 64x64 session's first real snapshots take the estimator 0.1-0.3 s each (factorisations of
#: a shape the warm-up did not have), and a following host's loop starts ~1 s of snapshots late:
#: with one waiting place, 113 of the 133 snapshots a following host did not estimate were in its
#: first second; with 1 s, four following runs lost 11-112 (95.1-99.8 % estimated), with 2 s 0-36
#: (98.1-99.96 %). The estimator has the capacity to catch up after (~200 a second against 145),
#: so the live view and the publishers lag by at most this long while it does. Never more than
#: `ESTIMATE_BACKLOG_MAX` snapshots (the snapshots are the ones `capsheet host`'s 2 s queue held).
ESTIMATE_BACKLOG_S = 2.0
ESTIMATE_BACKLOG_MAX = 1024


class SessionOutputs:
    """What ``--record``/``--live``/``--can-log`` ask of one session.

    Parameters
    ----------
    args : argparse.Namespace
        With ``record``, ``live``, ``live_rate`` and optionally ``can_log``.
    lattice : protocol.lattice.Lattice
    link_length : float
        Metres.
    mode : str
        ``"host"``, ``"demo"`` or ``"tactile"`` (stored in the session metadata).
    colour_by : str
        `host.publish.live.COLOUR_MODES`.
    prog : str
        For messages.
    """

    def __init__(self, args, lattice, link_length: float, *, mode: str, colour_by: str = "links",
                 session: dict | None = None, layout: dict | None = None, calibration: dict | None = None,
                 prog: str = "capsheet") -> None:
        self.prog = prog
        self.lattice = lattice
        self.link_length = float(link_length)
        self.recorder = None
        self.publisher = None  #: `host.publish.zenoh_pub.ZenohPublisher` (``--publish zenoh``)
        self.session_facts = {"mode": mode, **(session or {})}  #: what the session says of itself
        self.ros2 = None  #: `host.publish.ros2.Ros2Outputs` (``--publish ros2``, ``--record-ros2``)
        #: ``--publish zenoh`` publishes this session's estimates (not with ``--no-publish-estimates``)
        self.publishes_estimates = not getattr(args, "no_publish_estimates", False)
        self._host = None
        self.can_log = None
        self._can_lock = threading.Lock()
        self.can_frames_logged = 0
        self.can_frames_sent_logged = 0  #: of those, frames this host sent (Tx)
        self._period = 1.0 / float(getattr(args, "live_rate", 20.0) or 20.0)
        self._last_est = self._last_unc = -np.inf
        self._previous = None
        self._fused = None  # 6/9-axis chips: the fused estimator, fed every snapshot in order
        self.estimates_skipped, self._skip_reason = 0, ""
        self.worker = None  #: `host.workers.estimate_worker.EstimatorProcess` (``--estimate-process``)
        self._worker_wanted = bool(getattr(args, "estimate_process", False))
        self._sent: dict[int, object] = {}  # counter -> snapshot, in the estimator process
        # snapshots due an estimate while the estimator process is full, oldest first (`ESTIMATE_BACKLOG_S`)
        self._waiting: deque = deque()
        self._next_est = -np.inf
        self.estimates_made = 0  #: estimates made (either path) and handed to the outputs
        self.estimates_not_made = 0  #: snapshots due an estimate that found the estimator process full
        self.records_at_emission = False  #: `attach` records every emitted snapshot itself
        record, live = getattr(args, "record", None), getattr(args, "live", None)
        if record or live is not None:
            import host.analysis.estimator  # noqa: F401 -- now, not at the first estimate: importing scipy

            # mid-session (~0.8 s holding the GIL) stalls the live path it runs in
            from host.record import recording as R
            split_mb, split_s = getattr(args, "split_size", None), getattr(args, "split_duration", None)
            if record and (split_mb or split_s) and R.split_path(record, 0).exists() \
                    and not getattr(args, "overwrite", False):
                raise SystemExit(f"{prog}: {R.split_path(record, 0)} exists (a split recording): give --overwrite "
                                 f"to replace it, or another --record name")
            live_session = mode == "host"  # the file gets the derived estimates and scene at a lower rate
            try:
                self.recorder = R.open_recorder(
                    record, lattice, link_length, process=getattr(args, "record_process", None), session={"mode": mode, **(session or {})},
                    live_port=live, colour_by=colour_by, layout=layout, calibration=calibration,
                    split_size=None if not split_mb else int(split_mb * 1e6), split_duration=split_s,
                    min_free=int(float(getattr(args, "min_free", 0.0) or 0.0) * 1e6) if record else 0,
                    on_stop=self._recording_stopped,
                    estimate_file_period_s=R.ESTIMATE_FILE_PERIOD_S if live_session else 0.0,
                    scene_file_period_s=R.SCENE_FILE_PERIOD_S if live_session else 0.0,
                    live_options=live_options(args) if live is not None else None)
            except OSError as exc:  # an unwritable --record path, a --live port in use
                what = "" if "live view" in str(exc) else f"cannot write {record}: "
                raise SystemExit(f"{prog}: {what}{exc}") from None
            except ValueError as exc:  # too little free space
                raise SystemExit(f"{prog}: {exc}") from None
            if self.recorder.live is not None:
                print(f"{prog}: live 3D view on {self.recorder.live.url} (Foxglove: Open connection -> "
                      f"Foxglove WebSocket -> {self.recorder.live.url})", file=sys.stderr)
        publish = getattr(args, "publish", None)
        record_ros2 = getattr(args, "record_ros2", None)
        if (publish is not None and publish[0] == "ros2") or record_ros2:
            self._open_ros2(args, lattice, publish, record_ros2, prog)
        if publish is not None and publish[0] == "zenoh":
            import host.analysis.estimator  # noqa: F401,F811 -- now, not mid-session (above)
            from host.publish.zenoh_pub import ZenohPublisher
            sheet = getattr(args, "sheet_name", "sheet")
            try:
                self.publisher = ZenohPublisher(sheet, publish[1], lattice, link_length,
                                                info={"mode": mode, **(session or {})},
                                                config_file=getattr(args, "zenoh_config", None))
            except ValueError as exc:  # a Zenoh config that cannot be used
                print(f"{prog}: {exc}", file=sys.stderr)
                raise SystemExit(2) from None
            except OSError as exc:
                raise SystemExit(f"{prog}: {exc}") from None
            print(f"{prog}: publishing to Zenoh under {self.publisher.prefix}/ "
                  f"({where_zenoh(publish[1], args)})", file=sys.stderr)
        if self._worker_wanted and (self.recorder is not None or self.publisher is not None or self.ros2 is not None):
            from host.workers.estimate_worker import EstimatorProcess
            self.worker = EstimatorProcess(lattice.rows, lattice.cols, self.link_length)
        path = getattr(args, "can_log", None)
        if path:
            import can
            try:
                Path(path).parent.mkdir(parents=True, exist_ok=True)
                self.can_log = can.Logger(path)
            except OSError as exc:
                raise SystemExit(f"{prog}: cannot write {path}: {exc}") from None
            self.can_log_path = path

    def _open_ros2(self, args, lattice, publish, record_ros2, prog: str) -> None:
        import host.analysis.estimator  # noqa: F401 -- now, not mid-session (above)
        from host.publish.ros2 import ROS_NAME, TOPICS, Ros2Outputs, domain_id
        sheet = getattr(args, "sheet_name", "sheet")
        if not ROS_NAME.match(sheet):
            print(f"{prog}: --sheet-name {sheet!r} is not a ROS 2 name (--publish ros2, --record-ros2): 1-64 of "
                  f"A-Z a-z 0-9 _, starting with a letter", file=sys.stderr)
            raise SystemExit(2)
        try:
            domain = domain_id()
        except ValueError as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
        ros2_pub = publish is not None and publish[0] == "ros2"
        try:
            self.ros2 = Ros2Outputs(sheet, lattice, publish=ros2_pub, endpoint=publish[1] if ros2_pub else None,
                                    record=record_ros2, domain=domain, config_file=getattr(args, "zenoh_config", None))
        except ValueError as exc:  # a Zenoh config that cannot be used
            print(f"{prog}: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
        except OSError as exc:
            # a file's own error (PermissionError ...) is the recording's; a plain OSError says what failed
            what = f"cannot write {record_ros2}: " if record_ros2 and type(exc) is not OSError else ""
            raise SystemExit(f"{prog}: {what}{exc}") from None
        self._ros2_info = {"format": "capsheet-ros2-info", "version": 1, "sheet": sheet, "rows": lattice.rows,
                           "cols": lattice.cols, "links": lattice.n_links, "link_length_m": self.link_length,
                           "layout": None, "calibration": None, "session": dict(self.session_facts),
                           "topics": {t: {"name": self.ros2.fq(t), "type": typ} for t, typ in TOPICS.items()}}
        self.ros2.info(self._ros2_info)  # before bring-up: no layout, no calibration yet
        if ros2_pub:
            print(f"{prog}: publishing ROS 2 messages (rmw_zenoh layout, domain {domain}) under "
                  f"{self.ros2.namespace}/ and /diagnostics ({where_zenoh(publish[1], args)})", file=sys.stderr)

    def _recording_stopped(self, reason: str) -> None:
        print(f"{self.prog}: recording stopped: {reason}; {self.recorder.paths[-1]} is complete and readable "
              f"(the session goes on{', the live view too' if self.recorder.live is not None else ''})",
              file=sys.stderr)

    @property
    def active(self) -> bool:
        return (self.recorder is not None or self.can_log is not None or self.publisher is not None
                or self.ros2 is not None)

    # -- wiring --------------------------------------------------------------------------------
    def attach(self, host) -> None:
        """Before bring-up: record the raw input of every transport and every SYNC the host opens."""
        from host.transport.ports import CanTransport

        self._host = host
        if self.publisher is not None:  # every snapshot as emitted, corrected, as the recording
            host.feed.add_listener(self.publisher.snapshot)
        if self.ros2 is not None:
            host.feed.add_listener(self.ros2.snapshot)
        if self.recorder is not None and self.recorder.path is not None:
            self.recorder.tap(host.transports, host.feed)
            self.recorder.tap_sync(host.feed)
            # every snapshot as it is emitted, corrected (the feed's listeners run in order with
            # the raw input): a consumer that falls behind drops from its queue, never from the file
            host.feed.add_listener(self.recorder.snapshot)
            self.records_at_emission = True
        if self.can_log is not None:
            cans = [t for t in host.transports if isinstance(t, CanTransport)]
            if not cans:
                print(f"{self.prog}: --can-log needs a CAN bus (--can); nothing is logged", file=sys.stderr)
            for t in cans:
                bus = host.transports.index(t)
                t.begin_capture(lambda cap, bus=bus: self._log_can(bus, cap))
                print(f"{self.prog}: CAN log channel {bus} ({'can%d' % bus} in .log) is {t.name}", file=sys.stderr)

    def _log_can(self, bus: int, cap) -> None:
        """A capture (`host.transport.ports.Capture`) of bus index ``bus`` into the log: one python-can
        message per frame, copied (the bus's own messages are not touched), the channel the bus
        index (ASC and BLF number channels; candump's .log shows it as ``can<index>``). What the
        host sent is logged as Tx (``is_rx`` False: candump's ``T``, ASC's ``Tx``), received frames
        as Rx; a received echo of the host's own frame (udp_multicast) is its Tx already."""
        import can

        sent = cap.direction == "tx"
        frames = cap.raw if sent else cap.frames()
        with self._can_lock:
            for f in frames:
                self.can_log.on_message_received(can.Message(
                    timestamp=float(f.timestamp or cap.wall_time), arbitration_id=int(f.arbitration_id),
                    is_extended_id=bool(f.is_extended_id), is_remote_frame=bool(f.is_remote_frame),
                    is_error_frame=bool(f.is_error_frame), is_fd=bool(f.is_fd),
                    bitrate_switch=bool(getattr(f, "bitrate_switch", False)),
                    dlc=getattr(f, "dlc", None) if f.is_remote_frame else None,
                    data=None if f.is_remote_frame else bytes(f.data), channel=bus, is_rx=not sent))
                self.can_frames_logged += 1
                self.can_frames_sent_logged += sent

    def describe(self, host) -> None:
        """After bring-up: the session's facts (layout, calibration, rate) into the recording."""
        if self.recorder is not None:
            self.recorder.add_host_facts(host)
        if self.publisher is not None or self.ros2 is not None:
            from host.record.recording import Recorder
            session, layout, calibration = Recorder.session_facts(host)
            live_cal = host.calibration
            if live_cal is not None:  # `--calibration`: what the snapshots were corrected with
                calibration = {**calibration, "host_calibration": live_cal.to_dict()}
            if self.publisher is not None:
                self.publisher.describe(layout, calibration, session)
            if self.ros2 is not None:
                self._ros2_info.update(layout=layout, calibration=calibration)
                self._ros2_info["session"].update(session or {})
                self.ros2.info(self._ros2_info)

    def snapshot(self, snap, *, truth: np.ndarray | None = None, displacement=None, force: bool = False,
                 estimate: bool = True):
        """Record ``snap``; estimate it (at most ``--live-rate`` per second, or when ``force``) for the
        recording and the live view. ``estimate=False``: record only (a newer snapshot is waiting:
        the estimate is for the newest, the recording for every one). Returns the estimate made, or
        None."""
        rec = self.recorder
        self._health()
        if rec is None and self.ros2 is None and (self.publisher is None or not self.publishes_estimates):
            return None  # nothing takes this session's estimates (workers make them: --no-publish-estimates)
        if rec is not None and rec.path is not None and not self.records_at_emission:
            rec.snapshot(snap)
        fused = None
        if getattr(snap, "gyro", None) is not None:  # 6/9-axis chips: the gyroscopes drive the shape
            #, so the fused estimator takes every snapshot in order, shown at the live rate
            from host.analysis.motion.snapshots import fused_update
            if self._fused is None:
                from host.analysis.motion import MotionEstimator
                self._fused = MotionEstimator(self.lattice.rows, self.lattice.cols, self.link_length)
            fused = fused_update(self._fused, snap)
            self.imu(snap, fused, self._fused)
            if fused is None:
                return None
        if self.worker is not None and fused is None:
            self._to_worker(snap, force)
            return None
        if not estimate:
            return None
        now = time.monotonic()
        if not (force or now - self._last_est >= self._period) or not snap.valid.any():
            return None
        self._last_est = now
        if fused is not None:
            self.publish(fused, snap, truth=truth, displacement=displacement)
            return fused
        from host.analysis.estimator import estimate as estimate_shape

        try:  # a dead or saturated chip is masked out, not fatal to the session
            est = estimate_shape(snap.readings, self.lattice.rows, self.lattice.cols, self.link_length, valid=snap.valid,
                           previous=self._previous, bad_readings="mask")
        except ValueError as exc:  # e.g. every valid link's reading is bad: counted, reported at close
            self.estimates_skipped += 1
            self._skip_reason = str(exc)
            return None
        self._previous = est
        self.estimates_made += 1
        unc = now - self._last_unc >= UNCERTAINTY_PERIOD_S
        if unc:
            self._last_unc = now
        self.publish(est, snap, truth=truth, displacement=displacement, uncertainty=unc)
        return est

    def imu(self, snap, fused=None, estimator=None) -> None:
        """A snapshot of 6/9-axis chips to ``--publish ros2`` / ``--record-ros2`` as the links'
        ``sensor_msgs/msg/Imu`` (and ``MagneticField``): with ``fused`` (`fused_update`'s shape of
        this snapshot, made by ``estimator``, a `host.analysis.motion.MotionEstimator`) their
        orientations and covariances, else none."""
        if self.ros2 is None or getattr(snap, "gyro", None) is None:
            return
        if fused is None or estimator is None:
            self.ros2.imu(snap, noise=None if estimator is None else estimator.config)
        else:
            self.ros2.imu(snap, fused.motion, estimator.orientation_cov(), estimator.config)

    # -- the estimator process (--estimate-process) ---------------------------------------------
    def _to_worker(self, snap, force: bool = False) -> None:
        """Every snapshot is a candidate (the estimator process keeps up, in order): sent when its
        turn under --live-rate comes and the process has room, else it waits behind the others
        waiting (`ESTIMATE_BACKLOG_S` of them at most: past it the oldest is given up, counted).
        The turn is on the snapshots' own times (their SYNC), not on when this thread gets to them:
        the main thread takes queued snapshots in bursts, and a burst must not read as a rate over
        --live-rate (a credit of `ESTIMATE_CREDIT_S` absorbs the SYNCs' jitter: a SYNC sent late
        and the next on time are closer than a period)."""
        self.poll()
        if not snap.valid.any():
            return
        t = float(snap.timestamp)
        if not force and t < self._next_est:
            return
        self._next_est = max(self._next_est, t - max(self._period, ESTIMATE_CREDIT_S)) + self._period
        if self._waiting or not self.worker.free:
            w = self._waiting
            while w and (len(w) >= ESTIMATE_BACKLOG_MAX or float(w[0].timestamp) < t - ESTIMATE_BACKLOG_S):
                w.popleft()
                self.estimates_not_made += 1  # waited longer than the backlog holds
            w.append(snap)
            return
        self._send(snap, time.monotonic())

    def _send(self, snap, now: float) -> None:
        unc = self.worker.uncertainty_due(now, UNCERTAINTY_PERIOD_S)
        self._sent[int(snap.counter)] = snap
        self.worker.submit(snap, uncertainty=unc)

    def poll(self, timeout_s: float = 0.0) -> int:
        """Hand the estimator process's finished estimates to the outputs (in order), send the
        snapshot waiting if there is room. Returns how many were handed on (0 without the process)."""
        if self.worker is None:
            return 0
        done = self.worker.results(timeout_s)
        self._publish_remote(done)
        while self._waiting and self.worker.free:
            self._send(self._waiting.popleft(), time.monotonic())
        return len(done)

    def _publish_remote(self, done) -> None:
        for est in done:
            snap = self._sent.pop(est.counter, None)
            if snap is None:
                continue
            if est.error:
                self.estimates_skipped += 1
                self._skip_reason = est.error
                continue
            self.estimates_made += 1
            self.publish(est, snap, uncertainty="joint_std" in est.__dict__)

    def estimate_counts(self) -> dict:
        """How the session's estimates went: made, not made (the estimator process full or a bad
        snapshot), and where they were made."""
        out = {"made": self.estimates_made, "skipped_bad": self.estimates_skipped,
               "where": "process" if self.worker is not None else "in process"}
        if self.worker is not None:
            out.update(not_made_busy=self.estimates_not_made, estimator_busy_s=round(self.worker.busy_s, 3),
                       uncertainties=self.worker.uncertainties, estimator_pid=self.worker.pid,
                       held_links=self.worker.held_links, held_estimates=self.worker.held_estimates)
        return out

    def output_counts(self) -> dict:
        """For the summary (``--json``): ``estimates`` (`estimate_counts`) when anything takes them,
        ``recorded`` (messages in the file per topic) with ``--record``."""
        out = {}
        if self.wants_estimates:
            out["estimates"] = self.estimate_counts()
        if self.recorder is not None and self.recorder.path is not None:
            c = self.recorder.counts
            out["recorded"] = {"snapshots": c.get("/capsheet/snapshot", 0), "estimates": c.get("/capsheet/estimate", 0)}
        return out

    def emit(self, snap) -> None:
        """A snapshot no host feed carries (``capsheet replay``): to ``--publish`` and ``--record-ros2``
        as `attach` sends a live host's."""
        if self.publisher is not None:
            self.publisher.snapshot(snap)
        if self.ros2 is not None:
            self.ros2.snapshot(snap)

    @property
    def wants_estimates(self) -> bool:
        """Something takes estimates: the recording, the live view or a publisher."""
        return (self.recorder is not None or self.ros2 is not None
                or (self.publisher is not None and self.publishes_estimates))

    def publish(self, est, snap, *, truth: np.ndarray | None = None, displacement=None,
                uncertainty: bool = False) -> None:
        """Record, show and publish an estimate made elsewhere (the demo's own)."""
        if self.publisher is not None and self.publishes_estimates:
            self.publisher.estimate(est, snap, uncertainty=uncertainty)
        if self.ros2 is not None:
            self.ros2.estimate(est, snap, uncertainty=uncertainty)
        if self.publisher is not None or self.ros2 is not None:
            self._health()
        if self.recorder is None:
            return
        err = err_mean = None
        if truth is not None:
            from host.analysis.estimator import error_percent_of_side
            err = error_percent_of_side(est.joints, truth, self.link_length)
            err_mean = float(np.mean(err))
        self.recorder.estimate(est, snap.counter, snap.timestamp, snap.wall_time, error_joint=err,
                               error_pct_side=err_mean, displacement=displacement, uncertainty=uncertainty)
        self.recorder.imu(snap, est)  # 6/9-axis chips: their axes beside the shape (live view)

    def tactile(self, k: int, frame, truth=None) -> None:
        """One `host.analysis.tactile.TactileFrame` (number ``k``): its estimate coloured by
        displacement, and its contacts (with the true contacts, ``(force, index)``, if known)."""
        rec = self.recorder
        wall = time.time()
        if self.ros2 is not None:  # the estimate (joints, surface) and the contacts, every frame
            self.ros2.estimate(frame.estimate, wall_time=wall)
            self.ros2.contacts(k, frame.contacts, frame.total_force_n, wall_time=wall)
        if self.publisher is not None:  # the same to capsheet/<sheet>/estimate and contacts, numbered by frame
            t_s = float(frame.t_s) if frame.t_s is not None else float("nan")
            if self.publishes_estimates:
                self.publisher.estimate(frame.estimate, SimpleNamespace(counter=k, timestamp=t_s, wall_time=wall),
                                        uncertainty=False)
            self.publisher.contacts(k, frame.t_s, wall, frame.total_force_n, contact_dicts(frame.contacts))
        if self.ros2 is not None or self.publisher is not None:
            self._health()
        if rec is None:
            return
        t = float(frame.t_s) if frame.t_s is not None else float(k)
        rec.estimate(frame.estimate, k, t, None, displacement=frame.displacement)
        cs = contact_dicts(frame.contacts)
        if truth:
            marks = [(m.force_n, m.index) if hasattr(m, "force_n") else m for m in truth]  # TrueMark or (F, i)
            cs += [{"id": "truth", "true": True, "index": [float(v) for v in i], "force_n": float(F),
                    "position": None} for F, i in marks]
        rec.contacts(k, t, cs)

    def _health(self, *, force: bool = False) -> None:
        """The host's summary to ``capsheet/<sheet>/health`` (about once a second)."""
        if self._host is None:
            return
        if self.publisher is not None:
            self.publisher.health(self._host.summary(), force=force)
        if self.ros2 is not None:
            self.ros2.health(self._host.summary(), force=force)

    def flush(self) -> None:
        if self.recorder is not None:
            self.recorder.flush()

    def close(self, stats: dict | None = None) -> None:
        if self.worker is not None:  # the estimates in flight first: they go to the outputs below
            self.estimates_not_made += len(self._waiting)
            self._waiting.clear()
            self._publish_remote(self.worker.close())
            self.estimates_not_made += len(self._sent)
            self._sent.clear()
        if self.publisher is not None:
            try:
                self._health(force=True)  # the final summary
            finally:
                self.publisher.close()
                c = self.publisher.counts
                touch = f"{c['contacts']} contact frames, " if c["contacts"] else ""
                print(f"{self.prog}: published {c['snapshot']} snapshots, {c['estimate']} estimates, {touch}"
                      f"{c['health']} health reports to Zenoh ({c['info']} info queries answered)",
                      file=sys.stderr)
                self.publisher = None
        if self.ros2 is not None:
            try:
                self._health(force=True)
            finally:
                self.ros2.close()
                c, r = self.ros2.counts, self.ros2
                what = " and ".join((["published"] if r.publisher is not None else [])
                                    + ([f"recorded to {r.recorder.path}"] if r.recorder is not None else []))
                imu = (f", {c['imu']} link IMU and {c['mag']} magnetic field messages"
                       if c["imu"] or c["mag"] else "")
                print(f"{self.prog}: {what} ROS 2 messages: {c['snapshot']} snapshots, {c['joints']} joints and "
                      f"surfaces, {c['contacts']} contact frames, {c['/diagnostics']} diagnostics{imu}", file=sys.stderr)
                for sink, n in r.failed.items():
                    if n:
                        print(f"{self.prog}: {n} ROS 2 messages could not be "
                              f"{'published' if sink == 'publish' else 'recorded'} ({r.last_error[sink]})",
                              file=sys.stderr)
                self.ros2 = None
        if self.recorder is not None:
            self.recorder.close(stats)
            if self.recorder.path is not None:
                c = self.recorder.counts
                files = self.recorder.paths
                where = files[0] if len(files) == 1 else f"{len(files)} files, {files[0]} .. {files[-1].name}"
                what = [f"{c.get(t, 0)} {name}" for t, name in (("/capsheet/snapshot", "snapshots"),
                                                                ("/capsheet/estimate", "estimates"),
                                                                ("/capsheet/contacts", "contact frames"))
                        if c.get(t, 0) or name == "snapshots"]
                print(f"{self.prog}: recorded {', '.join(what)} to {where}", file=sys.stderr)
                if self.recorder.stopped:
                    print(f"{self.prog}: the recording stopped early ({self.recorder.stopped}); "
                          f"{self.recorder.not_recorded} messages after it were not recorded", file=sys.stderr)
            if self.estimates_skipped:
                print(f"{self.prog}: {self.estimates_skipped} snapshots could not be estimated "
                      f"(last: {self._skip_reason})", file=sys.stderr)
        if self.can_log is not None:
            self.can_log.stop()
            print(f"{self.prog}: logged {self.can_frames_logged} CAN frames ({self.can_frames_sent_logged} sent by "
                  f"this host) to {self.can_log_path}", file=sys.stderr)
