"""``capsheet demo``: the main job end to end, no hardware, no flags.

A virtual 14x14-joint sheet runs on a real pseudo-terminal (its gateway speaks the serial protocol);
the host opens that port with pyserial, discovers and assigns every chip, drives SYNC, aggregates
snapshots, estimates the shape of every snapshot live and compares it with the virtual truth.
It writes a PNG of estimated vs true shape.

Pass rule (exit 0): the mean joint error of the complete snapshots compared with the truth is within
``--target`` (default 1 % of the side length) AND at least ``--min-complete`` (default 99 %) of
the SYNCs sent gave a complete snapshot of the whole sheet (`whole_sheet`: a chip marked silent is a
link missing). Otherwise exit 1 (2 for bad options). The host takes the
newest snapshot when estimation falls behind (newest wins; the skipped ones are counted).
The virtual gateway stands for a 12 Mbaud UART (what 364 chips at 145 Hz need, per-chip).

6/9-axis chips (``--sensors accel+gyro`` or ``accel+gyro+mag``, docs/protocol.md §16) on a moving
sheet (``--shape carry|wave|elbow|tap|flat_turn``, docs/motion.md): the host asks for IMU records
(CONFIG_IMU) and shapes every snapshot, in order, with the fused estimator (docs/estimator.md §8)
(`host.analysis.motion.MotionEstimator`: gyroscopes as the process model, the chips' sample times)
in a process of its own (`host.workers.fused_worker.FusedProcess`: in the host's, it took the
interpreter lock from the receive threads, and on a busy machine one gateway's frames came too late);
the same pass rule. The moving sheet lies at its scene's start through the bring-up and moves from
the first SYNCs on (`virtual_sheet.imu_source.ImuSource.hold`): the estimator's first snapshot takes
the sheet as still, and the error no longer depends on how long the bring-up took.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np


#: the UART rate each virtual gateway stands for (a pty has none): what 364 chips at 145 Hz need
GATEWAY_BAUD = 12_000_000


def register(sub) -> None:
    from host.cli import argtypes as T
    p = sub.add_parser(
        "demo", help="the main job on a virtual sheet: pty serial -> host -> live shape estimate -> PNG",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shape", default="grow",
                   help="scene or shape of the virtual sheet (grow, tilt, press, gaussian, sphere, ...; the moving "
                        "sheets carry, wave, elbow, tap, flat_turn; default grow)")
    p.add_argument("--lattice", type=T.lattice, default="14x14", help="joints, ROWSxCOLS (default 14x14)")
    p.add_argument("--link-length", type=T.link_length, default=0.01, help="metres (default 0.01)")
    p.add_argument("--noise", type=T.noise, default=1.0, help="sensor noise, %% of g per axis (default 1)")
    p.add_argument("--rate", type=T.rate, default=145.0, help="SYNC rate, Hz (default 145, the paper's)")
    p.add_argument("--min-complete", type=T.percent, default=99.0,
                   help="%% of SYNCs that must give a complete snapshot to pass (default 99)")
    p.add_argument("--duration", type=T.duration, default=6.0, help="seconds of live streaming (default 6)")
    p.add_argument("--packed", action="store_true", help="the gateway packs SNAPSHOT frames instead of per-chip SAMPLEs")
    p.add_argument("--gateways", type=T.int_range(1, 64), default=None, metavar="N",
                   help="the sheet behind N serial gateways, each on its own pty with a block of the links, "
                        "merged by the host into one lattice (default 1; 32x32 at 145 Hz needs 2, packed; "
                        "with --sensors as many as the IMU records need: 14x14 9-axis at 145 Hz, 2)")
    p.add_argument("--target", type=T.positive_float, default=1.0, help="max mean joint error, %% of side (default 1)")
    p.add_argument("--out", type=T.figure_file, default="out/demo.png",
                   help="PNG of estimated vs true shape (default out/demo.png)")
    p.add_argument("--calibration", metavar="CAL_JSON", type=T.existing_file(".json", what="a calibration file"),
                   help="apply this calibration (capsheet calibrate) to every snapshot")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (alone on stdout; messages on stderr)")
    p.add_argument("--seed", type=T.seed, default=1, help="seed of the sheet's uids and noise (default 1)")
    p.add_argument("--learn-layout", action="store_true",
                   help="the sheet's chips carry their uids on links in a random order and go through the poses of "
                        "`capsheet layout learn` on a timer, from when the host starts listening (the sheet lies flat "
                        "until then); the host learns the layout from them first (the truth "
                        "only scores it: layout_links_correct of layout_links), then streams with it. Passing needs "
                        "every link right too (replaces --shape; accelerometer chips)")
    from host.cli.sensor_args import add_sensor_args
    add_sensor_args(p)  # --sensors, --gyro-range, --mag-range
    from host.cli.record_args import add_record_args
    add_record_args(p)  # --record FILE.mcap, --live [PORT]
    p.set_defaults(func=run)


#: snapshots waiting for room in the fused estimator's process, at most (6 s at 145 Hz, ~30 MB of a
#: 14x14 sheet's): past it the oldest is given up (counted in the summary's ``fused.not_sent``)
FUSED_WAITING_MAX = 870
#: the fused estimator's process runs this much nicer than the demo: on a busy machine it falls
#: behind and catches up (its shapes come late, none is lost) while the receive threads keep the
#: processor (a frame read late is lost to its snapshot)
FUSED_NICE = 5
#: after streaming, how long the fused estimator's process is given for what still waits (s)
FUSED_DRAIN_S = 30.0

#: --learn-layout: how much longer than the learner needs each pose is held (s): snapshots that
#: come late or are lost on a busy machine (a pose missed costs a cycle of the poses, not the layout)
LEARN_MARGIN_S = 0.4
#: --learn-layout: seconds the sheet spends moving from one pose to the next
LEARN_MOVE_S = 0.5


def learn_detector():
    """The pose detector the demo's learner runs (`collect_poses` is given its ``settle_s``): the
    detector's own defaults, as ``capsheet layout learn``'s."""
    from host.analysis.layout.poses import PoseDetector
    return PoseDetector()


def learn_hold_s() -> float:
    """Seconds each --learn-layout pose is held: what the learner needs to take it (its still window,
    ``settle_s``, and one chunk more, since the window's chunks need not begin with the hold) and
    `LEARN_MARGIN_S`."""
    det = learn_detector()
    return det.settle_s + det.chunk_s + LEARN_MARGIN_S


class CuedPoses:
    """The layout poses (`virtual_sheet.layout_poses.LayoutPoseScene`) on a timer that starts at a
    cue: the sheet lies in the first pose (flat) until `begin`, then goes through the poses from
    there, over and over. The demo gives the cue when its learner starts listening (after the
    bring-up, however long that took), so the first pass of the poses is the one the learner takes
    and nobody waits for the timer to come round to flat (up to a whole pass, 8 s, with the timer
    started when the sheet's process did).

    No ``period_s``: the sheet solves each scene step once, as it comes (a pose is a few
    microseconds to solve), since a step before the cue and the same step of the timer differ.

    >>> from virtual_sheet.layout_poses import LayoutPoseScene
    >>> s = CuedPoses(LayoutPoseScene(3, 4, hold_s=2.0, move_s=1.0, jitter_rad=0.0))
    >>> [s.pose_at(t) for t in (0.5, 2.5, 30.0)]
    ['flat', 'flat', 'flat']
    >>> s.begin(29.0)
    >>> [s.pose_at(t) for t in (30.5, 31.5, 32.5)]
    ['flat', None, 'tilt']
    """

    def __init__(self, poses) -> None:
        self.poses = poses
        self.rows, self.cols, self.link_length = poses.rows, poses.cols, poses.link_length
        self.begin_at_s = math.inf

    def begin(self, at_s: float) -> None:
        """The poses' timer starts at ``at_s`` (the sheet's clock, seconds); once."""
        if self.begin_at_s != math.inf:
            raise ValueError(f"the poses began already, at {self.begin_at_s:g} s")
        self.begin_at_s = float(at_s)

    def _timer(self, t_s: float) -> float:
        return max(0.0, float(t_s) - self.begin_at_s) if self.begin_at_s != math.inf else 0.0

    def pose_at(self, t_s: float) -> str | None:
        return self.poses.pose_at(self._timer(t_s))

    def joints(self, t_s: float) -> np.ndarray:
        return self.poses.joints(self._timer(t_s))


def next_scene_step(now_s: float, rate_hz: float) -> float:
    """The first scene step after ``now_s`` (the sheet solves a step when a SYNC of its time comes,
    once): where the --learn-layout poses begin when cued at ``now_s``.

    >>> next_scene_step(3.34, 10.0), next_scene_step(3.3, 10.0)
    (3.4, 3.4)
    """
    return math.floor(now_s * rate_hz + 1.0) / rate_hz


def make_sheet(kwargs: dict):
    """The virtual sheet of `_sheet_kwargs` (``learn_layout``: the layout poses on a timer from the
    learner's cue, `CuedPoses`, the uids shuffled over the links), in the sheet's process and, for
    the truth, in the demo's."""
    from virtual_sheet.sheet import VirtualSheet
    kwargs = dict(kwargs)
    shape, lattice = kwargs.pop("shape"), kwargs.pop("lattice")
    if kwargs.pop("learn_layout", False):  # the poses, then (`switch_scene`) the demo's shape
        from virtual_sheet.layout_poses import LayoutPoseScene, PosesThenScene
        from virtual_sheet.shapes import make_scene
        poses = CuedPoses(LayoutPoseScene(lattice.rows, lattice.cols, kwargs["link_length"], hold_s=learn_hold_s(),
                                          move_s=LEARN_MOVE_S, seed=kwargs["seed"]))
        kwargs["scene"] = PosesThenScene(poses, make_scene(shape, lattice.rows, lattice.cols, kwargs["link_length"]))
        kwargs["shuffle_ids"] = True
        kwargs["scene"].precompute(kwargs["scene_rate_hz"])
    return VirtualSheet(shape, lattice, **kwargs)


def _sheet_kwargs(args) -> dict:
    # a moving scene is solved (exact Chebyshev net, ~25 ms) in 10 steps a second, each step once
    # (VirtualSheet.precompute before streaming); the truth of a counter is the very step its
    # readings came from, so error against truth is exact
    return dict(shape=args.shape, lattice=args.lattice, link_length=args.link_length, noise=args.noise,
                seed=args.seed, scene_rate_hz=10.0, sensors=getattr(args, "sensors", "accel"),
                learn_layout=bool(getattr(args, "learn_layout", False)))


def check_capacity(args) -> None:
    """Before anything starts: the sheet's traffic fits its gateways at ``--rate`` (each stands for a
    `GATEWAY_BAUD` UART), else a usage error whose remedy fits what is set (`capacity_remedy`)."""
    from host.cli.argtypes import usage_error
    from host.cli.transport_args import split_needed
    from host.session.core import capacity_remedy
    from protocol.capacity import bus_load

    fmt = {"accel": 0, "accel+gyro": 1, "accel+gyro+mag": 2}[getattr(args, "sensors", "accel")]
    if args.gateways is None:  # IMU records: as many 12 Mbaud gateways as they need
        need = split_needed(args.lattice.n_links, args.rate, kind="serial", bitrate=GATEWAY_BAUD, fmt=fmt,
                            packed=args.packed) if fmt else 1
        args.gateways = need or 64
    lat, g = args.lattice, args.gateways
    per = -(-lat.n_links // g)  # the largest block (VirtualSheet.split: contiguous, near equal)
    load = bus_load(per, args.rate, kind="serial", bitrate=GATEWAY_BAUD, packed=args.packed, fmt=fmt)
    if load <= 1.0:
        return
    def fits(packed: bool, start: int):
        return split_needed(lat.n_links, args.rate, kind="serial", bitrate=GATEWAY_BAUD, packed=packed, start=start,
                            fmt=fmt)
    more, k_packed = fits(args.packed, g + 1), (None if args.packed else fits(True, g))
    pack = None if k_packed is None else "--packed" if k_packed == g else f"--packed --gateways {k_packed}"
    remedy = capacity_remedy("serial", load, args.rate, packed=args.packed or pack is None, pack=pack,
                             split=f"--gateways {more}" if more else "more gateways than 64", faster=False)
    raise usage_error("capsheet demo", f"--rate {args.rate:g}: {lat.n_links:,} chips "
                      f"{'packed' if args.packed else 'per-chip'} over {g} gateway{'s' if g > 1 else ''} of "
                      f"{GATEWAY_BAUD / 1e6:g} Mbaud need {100 * load:.0f} % of each; {remedy}")


def _serve_virtual_sheet(kwargs: dict, packed: bool, gateways: int, layout_path: str, conn) -> None:
    """Child process: the virtual sheet on a pty, like a real sheet on its own hardware. Answers
    "truth" requests with the scene time of each SYNC counter it has seen since the last request."""
    from virtual_sheet.devices import PtyDevice

    try:
        sheet = make_sheet(kwargs)
        sheet.precompute()
        if sheet.imu_source is not None:  # a moving sheet lies at its start until the demo streams ("start")
            sheet.imu_source.hold()
        sheet.write_layout(layout_path)
        if gateways > 1:
            from virtual_sheet.devices import MultiPtyDevice
            device = MultiPtyDevice(sheet, n_gateways=gateways, packed=packed)
        else:
            device = PtyDevice(sheet, packed=packed)
    except Exception as exc:  # noqa: BLE001 - the parent says it in one line instead of waiting
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    sent: dict[int, float] = {}
    with device as dev:
        conn.send(("ready", list(getattr(dev, "paths", [str(dev.path)])), dev.describe()))
        # the device's clock on the machine's monotonic clock, which the host's is too (same machine)
        epoch = time.monotonic() - dev.now()
        while True:
            req = conn.recv()
            if req == "stop":
                break
            if req == "start":  # the host streams: the scene's motion begins now
                conn.send(("started", dev.call(lambda now_s: (sheet.imu_source.start_at(now_s), now_s)[1])))
                continue
            if req == "poses":  # --learn-layout: the learner listens, the poses' timer starts at the next step
                at = next_scene_step(dev.now(), sheet.scene_rate_hz)
                sheet.scene.poses.begin(at)
                conn.send(("posing", at))
                continue
            if req == "switch":  # --learn-layout: the layout is learned, the demo's shape from the next steps
                rate = sheet.scene_rate_hz
                at = math.ceil((dev.now() + 0.5) * rate) / rate
                sheet.scene.switch(at)
                conn.send(("switched", at))
                continue
            # what is new since the last request: a counter not sent, or sent before its wrap; with
            # when its chips took the SYNC to arrive (monotonic: the host compares it with when it sent it)
            now_kept = dict(sheet.sync_times)
            new = {c: (sheet.truth_time(c), epoch + t) for c, t in now_kept.items() if sent.get(c) != t}
            sent = now_kept  # bounded as the sheet's own (SYNC_TIMES_KEPT)
            conn.send(new)
    conn.send(("stopped",))


def usage_error_demo(msg: str) -> SystemExit:
    from host.cli.argtypes import usage_error
    return usage_error("capsheet demo", msg)


def learn_layout_over(paths, lat, begin=lambda: None) -> tuple[dict, float]:
    """``capsheet layout learn``'s session over the sheet's ptys: bring it up without a layout, cue
    the poses (``begin()``: the sheet starts them, `CuedPoses`), take them as they come, place the
    chips. Returns ({uid: link}, seconds taken)."""
    from host.analysis.layout import PROCEDURE, learn_layout
    from host.cli.layout import DEFAULT_RATE_HZ, collect_poses, open_host
    from host.transport.ports import open_transport

    t0 = time.monotonic()
    host = open_host([open_transport("serial", p, baudrate=GATEWAY_BAUD) for p in paths], lat, DEFAULT_RATE_HZ)
    with host:
        host.bring_up()
        begin()
        poses = collect_poses(host, PROCEDURE, settle_s=learn_detector().settle_s,
                              timeout_s=20 * (learn_hold_s() + LEARN_MOVE_S),
                              say=lambda s: print(f"capsheet demo: {s}", file=sys.stderr))
        host.stop()
    res = learn_layout(lat, poses)
    return res.layout, time.monotonic() - t0


def whole_sheet(snap) -> bool:
    """A snapshot the demo counts as complete: every expected link came (`LatticeSnapshot.complete`)
    and none of the sheet's chips is marked silent. The aggregator stops expecting a chip the watchdog
    marked silent, so that one dead chip does not hold every snapshot to its deadline; the demo's
    sheet has no dead chip, and a link missing that way is a link missing (half a sheet marked silent
    read "100 % complete" before).

    >>> from types import SimpleNamespace
    >>> whole_sheet(SimpleNamespace(complete=True, status=np.zeros(4, np.uint8)))
    True
    >>> whole_sheet(SimpleNamespace(complete=True, status=np.array([0, 0x20, 0, 0], np.uint8)))
    False
    >>> whole_sheet(SimpleNamespace(complete=False, status=np.zeros(4, np.uint8)))
    False
    """
    from host.snapshots.snapshot import LinkFlag
    return bool(snap.complete) and not (np.asarray(snap.status) & LinkFlag.SILENT).any()


def host_imu(args) -> bool:
    """The chips send IMU records (``--sensors`` with a gyroscope): the fused estimator shapes."""
    return getattr(args, "sensors", "accel") != "accel"


def _recent_ms(samples) -> float | None:
    """The median of the newest 50 of ``samples`` (seconds) in milliseconds; None before the first
    (the status line says n/a: a median of nothing was NaN and two numpy warnings on stderr).

    >>> from host.cli.runstats import Samples
    >>> s = Samples()
    >>> _recent_ms(s) is None
    True
    >>> s.add(0.002); s.add(0.004); s.add(0.010)
    >>> _recent_ms(s)
    4.0
    """
    recent = samples.recent(50)
    return 1e3 * float(np.median(recent)) if recent else None


def _fmt(v, spec: str = ".2f", unit: str = "") -> str:
    return "n/a" if v is None else f"{v:{spec}}{unit}"


def run(args) -> int:
    import multiprocessing as mp
    from host.cli import short_gil_switch
    short_gil_switch()  # the SYNC thread gets the interpreter lock within 0.5 ms, not 5 ms

    from host.analysis.motion.snapshots import fused_update
    from host.estimator import error_percent_of_side, estimate
    from host.cli.progress import LiveLine
    from host.cli.runstats import CompletenessWindow, Samples
    from host.session.core import Host, Layout
    from host.transport.ports import open_transport
    if args.learn_layout and getattr(args, "sensors", "accel") != "accel":
        raise usage_error_demo("--learn-layout runs the layout poses on accelerometer chips: drop --sensors")
    check_capacity(args)  # every other value was checked by its type (host.cli.argtypes)
    live = LiveLine(every_s=2.0)  # the status: a terminal one line redrawn; a log a line every 2 s
    from host.cli.calibrate import load_calibration_arg
    cal = load_calibration_arg(args.calibration, args.lattice, "capsheet demo")
    # The parent's own copy of the scene gives the truth for a scene time (deterministic).
    try:
        truth_sheet = make_sheet(_sheet_kwargs(args))
    except ValueError as exc:  # a shape that needs options the demo has not, a bad lattice: one line
        print(f"capsheet demo: {exc}", file=sys.stderr)
        return 2
    lat = truth_sheet.lattice
    rows, cols, L = lat.rows, lat.cols, args.link_length
    if truth_sheet.imu_source is not None:  # a periodic moving scene: its truth solved once, looked up live
        truth_sheet.precompute()
        # else each instant is solved when asked: one every 0.1 s, so one at a time (0.9 ms for a
        # 14x14 carried sheet), not the 0.1 s ahead a live sheet solves (29 instants, 4.6 ms, in
        # the thread that hands the fused estimator its snapshots)
        truth_sheet.imu_source.chunk = 1
    tmp = Path(tempfile.mkdtemp(prefix="capsheet-demo-"))
    layout_path = tmp / "layout.json"
    print(f"capsheet demo: virtual {rows}x{cols} sheet ({lat.n_links} chips), scene {args.shape!r}, "
          f"noise {args.noise:g} % g, SYNC at {args.rate:g} Hz{', packed' if args.packed else ''}"
          f"{f', {args.gateways} gateways' if args.gateways > 1 else ''}", file=sys.stderr)
    # bounded however long --duration is: exact count, mean, max; medians from a
    # uniform sample of at most 65,536 (host.cli.runstats)
    errors, times, latencies, sample_lags = Samples(), Samples(), Samples(), Samples()
    last = None
    truth_times: dict[int, float] = {}
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_serve_virtual_sheet,
                       args=(_sheet_kwargs(args), args.packed, args.gateways, str(layout_path), child), daemon=True)
    proc.start()
    n_est = 0
    fused = worker = None
    fused_stats: dict = {}
    elapsed = 0.0
    layout_score: dict = {}
    stats: dict = {}
    try:
        t_wait = time.monotonic()
        while not parent.poll(0.2):  # the sheet's process builds its scene: wait while it lives
            if not proc.is_alive():
                raise SystemExit(f"capsheet demo: the virtual sheet's process ended (exit {proc.exitcode}) "
                                 f"before it was ready")
            if time.monotonic() - t_wait > 300:
                raise SystemExit("capsheet demo: the virtual sheet did not start within 300 s")
        msg = parent.recv()
        if msg[0] != "ready":  # the sheet could not be built or its ptys opened: its one line
            raise SystemExit(f"capsheet demo: the virtual sheet did not start: {msg[1]}")
        _, paths, described = msg
        print(f"capsheet demo: virtual sheet (own process) on {described}; host opens it with pyserial",
              file=sys.stderr)

        def truth_of(snap) -> np.ndarray:
            counter = snap.counter
            if counter not in truth_times:
                parent.send("truth")
                truth_times.update(parent.recv())
                while len(truth_times) > 8192:  # counters never asked for (skipped snapshots): oldest out
                    del truth_times[next(iter(truth_times))]
            # used once: after the counter wraps, the same number is a new SYNC, asked for again
            t_scene, t_arrived = truth_times.pop(counter)
            # how long after the host sent (stamped) this SYNC the sheet's chips took it to arrive
            # (they sample then): on a wire ~0; on a pty the sheet's late reads less what its arrival
            # estimate takes back (docs/motion.md, "Time on a pty")
            sample_lags.add(t_arrived - snap.timestamp)
            return truth_sheet.joints_at_scene_time(t_scene)

        layout = Layout.load(layout_path)
        if args.learn_layout:  # the truth scores the learned layout, and the host streams with what it learned
            def begin_poses() -> None:  # the learner listens: the sheet's poses start (`CuedPoses`)
                parent.send("poses")
                _, at = parent.recv()
                truth_sheet.scene.poses.begin(at)  # the demo's copy keeps every instant's answer

            learned, learn_s = learn_layout_over(paths, lat, begin_poses)
            truth_links = {k: u for u, k in layout.links.items()}
            layout_score = {"layout_links": lat.n_links,
                            "layout_links_correct": sum(1 for u, k in learned.items() if truth_links.get(k) == u),
                            "layout_learn_s": round(learn_s, 1)}
            print(f"capsheet demo: layout learned in {learn_s:.1f} s: {layout_score['layout_links_correct']} of "
                  f"{lat.n_links} links right (the sheet's truth)", file=sys.stderr)
            layout = Layout(learned, f"{rows}x{cols}")
            parent.send("switch")  # the sheet leaves the poses for the demo's shape, which is scored
            _, at = parent.recv()
            truth_sheet.scene.switch(at)
            parent.send("truth")  # the learning session's SYNC counters: taken and dropped, the demo's start again at 0
            parent.recv()
        # a pty has no baud rate: the virtual gateway stands for a 12 Mbaud UART (capacity check)
        transports = [open_transport("serial", p, baudrate=GATEWAY_BAUD) for p in paths]
        # (counter, whole sheet) of every snapshot emitted, counted into the window of SYNCs the
        # demo measures once bring-up has set its first counter (those before it, held until then)
        window_lock = threading.Lock()
        window: list = [None]
        before_window: deque = deque(maxlen=4096)

        def on_snapshot(snap) -> None:
            whole = whole_sheet(snap)
            with window_lock:
                if window[0] is None:
                    before_window.append((snap.counter, whole))
                else:
                    window[0].add(snap.counter, whole)

        host = Host(transports, lat, layout=layout, rate_hz=args.rate, on_snapshot=on_snapshot)
        from host.cli.sensor_args import imu_config
        host.imu_config = imu_config(args)
        from host.cli.record_args import SessionOutputs
        outputs = SessionOutputs(args, lat, L, mode="demo", colour_by="error", prog="capsheet demo",
                                 session={"shape": args.shape, "noise_pct_g": args.noise, "seed": args.seed})
        outputs.attach(host)
        if host.imu_config is not None:  # the gyroscopes drive the shape
            from host.analysis.motion import FusedConfig, MotionEstimator
            from protocol.constants import G0
            # the virtual chips' accelerometer noise is --noise (1 % g by default), not the
            # datasheet's the estimator assumes: it is told
            config = FusedConfig(accel_noise_mps2=args.noise / 100.0 * G0)
            if outputs.ros2 is None:  # in its own process, started while the chips are brought up
                from host.workers.fused_worker import FusedProcess
                worker = FusedProcess(rows, cols, L, config=config, nice=FUSED_NICE)
            else:  # --publish ros2 / --record-ros2 publish every link's orientation from its state
                fused = MotionEstimator(rows, cols, L, config=config)
        if cal is not None:  # before bring-up: it follows the chip calibration the host reads
            host.set_calibration(cal)
        if worker is not None and not worker.wait_ready(120.0):
            raise SystemExit("capsheet demo: the fused estimator's process did not start within 120 s")
        with host:
            t_up = time.monotonic()
            summary = host.bring_up(packed=args.packed)
            if truth_sheet.imu_source is not None:
                # a moving sheet lay at its start through the bring-up, however long it took (the
                # fused estimator's first snapshot takes the sheet as still): it moves from now on
                parent.send("start")
                parent.recv()
            from host.cli.host import calibration_words
            print(f"capsheet demo: {summary['discovered']} chips discovered, {summary['assigned']} assigned, "
                  f"{calibration_words(host, summary)}, {summary['started']} streaming "
                  f"({time.monotonic() - t_up:.1f} s)", file=sys.stderr)
            outputs.describe(host)
            if summary["started"] < lat.n_links:
                print(f"capsheet demo: only {summary['started']} of {lat.n_links} chips started", file=sys.stderr)
            previous = None
            t0 = time.monotonic()
            first, sent0 = host.counter, host.syncs_sent  # the window: completeness counts its SYNCs only
            with window_lock:
                window[0] = CompletenessWindow(first)
                for c, ok in before_window:
                    window[0].add(c, ok)
                before_window.clear()
            last_eval = [0.0]
            agg = host.aggregator

            def took(snap, est, seconds: float) -> None:
                """An estimate of ``snap`` made in ``seconds``: counted, and scored against the truth."""
                nonlocal n_est, last
                times.add(seconds)
                n_est += 1
                latencies.add(time.monotonic() - snap.timestamp)
                # the truth: compare at most 10 complete snapshots/s (the error target is for a
                # complete sheet; an incomplete one is estimated and shown, not scored)
                if snap.complete and time.monotonic() - last_eval[0] >= 0.1:
                    last_eval[0] = time.monotonic()
                    truth = truth_of(snap)
                    err = error_percent_of_side(est.joints, truth, L)
                    errors.add(float(err.mean()))
                    last = (truth, est.joints, err, snap.counter)
                    outputs.publish(est, snap, truth=truth)

            # the fused estimator's process: every snapshot, in order; those it has no room for
            # yet wait here (`FUSED_WAITING_MAX` at most: past it the oldest is given up, counted)
            waiting: deque = deque()
            sent_snaps: dict = {}
            while time.monotonic() - t0 < args.duration:
                wait = min(0.5, max(0.0, args.duration - (time.monotonic() - t0)))
                if worker is not None:
                    snap = host.get(0.005 if waiting or sent_snaps else wait)
                    if snap is not None and snap.valid.any():
                        waiting.append(snap)
                        if len(waiting) > FUSED_WAITING_MAX:
                            waiting.popleft()
                            fused_stats["given_up"] = fused_stats.get("given_up", 0) + 1
                    while waiting and worker.free:
                        s = waiting.popleft()
                        worker.submit(s)
                        sent_snaps[s.counter] = s
                    for r in worker.results():
                        s = sent_snaps.pop(r.counter, None)
                        if r.ok and s is not None:
                            took(s, r, r.seconds)
                else:
                    # the fused estimator integrates the gyroscopes: every snapshot, in order
                    snap = host.latest(wait) if fused is None else host.get(wait)
                    if snap is None or not snap.valid.any():
                        continue
                    t_e = time.perf_counter()
                    if fused is not None:
                        est = fused_update(fused, snap)
                        outputs.imu(snap, est, fused)  # --publish ros2, --record-ros2: every link's IMU
                        if est is None:
                            continue
                    else:
                        est = estimate(snap.readings, rows, cols, L, valid=snap.valid, previous=previous)
                    previous = est
                    took(snap, est, time.perf_counter() - t_e)
                if live.due():
                    el = time.monotonic() - t0
                    # up to the newest SYNC emitted: those after it are in flight, not yet missed
                    c_now, n_now = host.counter, host.syncs_sent - sent0
                    with window_lock:
                        last_c = window[0].last_counter
                        end = (last_c + 1) & 0xFFFF if last_c is not None else first
                        win = window[0].result(end, n_now - ((c_now - end) & 0xFFFF))
                    live.show(f"{n_est / max(el, 1e-9):6.1f} estimates/s | latency "
                              f"{_fmt(_recent_ms(latencies), '6.1f', ' ms')} | estimate {_fmt(_recent_ms(times), '5.2f', ' ms')} | "
                              f"error {_fmt(errors.last)} % of side | "
                              f"complete {win['complete_pct']:5.1f} % of SYNCs")
            elapsed = time.monotonic() - t0
            end, sent_n = host.counter, host.syncs_sent - sent0
            host.stop()  # the SYNCs in flight get their chance to complete
            if worker is not None:  # the snapshots of the window still waiting or in flight are shaped
                t_end = time.monotonic() + FUSED_DRAIN_S
                while (waiting or sent_snaps) and time.monotonic() < t_end:
                    while waiting and worker.free:
                        s = waiting.popleft()
                        worker.submit(s)
                        sent_snaps[s.counter] = s
                    for r in worker.results(0.05):
                        s = sent_snaps.pop(r.counter, None)
                        if r.ok and s is not None:
                            took(s, r, r.seconds)
                worker.close(0.0)
                fused_stats.update(process=True, submitted=worker.submitted, made=worker.made,
                                   left_out=worker.left_out, refused=worker.failed,
                                   not_sent=len(waiting) + fused_stats.get("given_up", 0),
                                   unanswered=len(sent_snaps))
                worker = None
            with window_lock:
                win = window[0].result(end, sent_n)
            st = agg.stats
            # the window's SYNCs and their snapshots; snapshots_emitted: every one since bring-up
            # (what a --record file holds)
            stats = {"syncs_sent": win["syncs_sent"], "snapshots": win["snapshots"], "complete": win["complete"],
                     "snapshots_emitted": st.emitted, "skipped_newest_wins": st.dropped, **agg.completeness(),
                     "syncs_missed": host.stats["live"]["syncs_missed"], "deadline_ms": round(1e3 * agg.deadline_s, 2)}
            outputs.close(host.stats)
    finally:
        if worker is not None:
            worker.close(0.0)
        if proc.is_alive():
            parent.send("stop")
            proc.join(10)
            if proc.is_alive():
                proc.terminate()
    live.end()
    sent = stats.get("syncs_sent", 0)
    complete_pct = 100.0 * stats.get("complete", 0) / sent if sent else 0.0
    mean_err = errors.mean
    err_ok = mean_err is not None and mean_err <= args.target
    complete_ok = sent > 0 and complete_pct >= args.min_complete
    layout_ok = not args.learn_layout or (layout_score.get("layout_links_correct") == layout_score.get("layout_links"))
    ok = err_ok and complete_ok and layout_ok
    result = {**layout_score,
        "rate_hz": args.rate, "duration_s": args.duration, "packed": args.packed, **stats,
        "complete_pct_of_syncs": round(complete_pct, 2),
        "syncs_per_s": round(sent / max(elapsed, 1e-9), 1), "gateways": args.gateways,
        # the live estimate takes the newest snapshot (newest wins): fewer estimates than SYNCs
        "estimates": n_est, "estimates_per_s": round(n_est / max(elapsed, 1e-9), 1),
        "compared_with_truth": errors.count,
        "mean_error_pct_side": round(mean_err, 3) if mean_err is not None else None,
        "max_snapshot_error_pct_side": round(errors.max, 3) if errors else None,
        "median_latency_ms": round(1e3 * latencies.median(), 2) if latencies else None,
        "median_estimate_ms": round(1e3 * times.median(), 3) if times else None,
        # the SYNCs compared with the truth: how long after the host sent each the chips sampled it
        "sync_sample_lag_ms": ({"median": round(1e3 * sample_lags.median(), 2), "max": round(1e3 * sample_lags.max, 2)}
                             if sample_lags else None),
        # medians beyond 65,536 values are of a uniform sample of them: how many were left out
        "median_sample_cut": {"latency": latencies.cut, "estimate": times.cut},
        "target_pct_side": args.target, "min_complete_pct": args.min_complete,
        "sensors": getattr(args, "sensors", "accel"),
        "estimator": "fused" if host_imu(args) else "accel_only", **({"fused": fused_stats} if fused_stats else {}),
        "error_ok": err_ok, "complete_ok": complete_ok, **({"layout_ok": layout_ok} if args.learn_layout else {}),
        "pass": ok,
    }
    if last is not None:
        truth, est_joints, err, counter = last
        out = Path(args.out)
        from host.cli.figures import demo_figure
        import matplotlib.pyplot as plt
        why = [] if err_ok else [f"mean error {_fmt(mean_err, '.2f')} % > target {args.target:g} %"]
        if not complete_ok:
            why.append(f"{complete_pct:.1f} % of SYNCs complete < {args.min_complete:g} %")
        plt.close(demo_figure(out, truth, est_joints, err, shape=args.shape, noise_pct_g=args.noise,
                              rate_hz=args.rate, run_mean_error_pct=errors.mean, counter=counter,
                              link_length=L, sensors=getattr(args, "sensors", "accel"),
                              failed="; ".join(why) or None, compared=errors.count))
        result["png"] = str(out)
        print(f"capsheet demo: wrote {out}", file=sys.stderr)
    verdict = "PASS" if ok else "FAIL"
    line = (f"capsheet demo: {verdict}: mean joint error {_fmt(mean_err, '.3f')} % of side "
            f"(target <= {args.target:g} %{'' if err_ok else ': MISSED'}), {complete_pct:.1f} % of {sent} SYNCs "
            f"complete (need >= {args.min_complete:g} %{'' if complete_ok else ': MISSED'}); "
            + (f"layout learned: {layout_score.get('layout_links_correct')} of {layout_score.get('layout_links')} links "
               f"right{'' if layout_ok else ': MISSED'}; " if args.learn_layout else "")
            + f"SYNC at {args.rate:g} Hz ({result['syncs_per_s']}/s sent), shape estimated "
            f"{result['estimates_per_s']}/s ({n_est} estimates, "
            f"{'every snapshot in order, fused' if result['estimator'] == 'fused' else 'newest snapshot first'}), median latency "
            f"{_fmt(result['median_latency_ms'], '.1f', ' ms')}, estimate {_fmt(result['median_estimate_ms'], '.2f', ' ms')}")
    print(line, file=sys.stderr if args.json else sys.stdout)
    if args.json:
        print(json.dumps(result, indent=1))
    return 0 if ok else 1
