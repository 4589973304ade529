"""``capsheet tactile``: contacts and forces live, from the virtual foam sheet or a real sheet.

By default it runs in-process on the virtual foam block (`virtual_sheet.foam`): a 14x14 sheet,
L = 1 cm, 1 % g reading noise, a scripted press and release of two indenters (``--indenter
sphere-punch``: a sphere that slides slowly, then a flat punch; ``--indenter finger``: a finger
that presses and slides, then a second finger beside it, 2.5 link lengths apart). It first learns
the rest shape from an untouched period, then prints one status line per snapshot (count,
positions in lattice indices, forces with their standard deviations, footprints, track ids,
onsets and releases) and writes a PNG heat map of the normal displacement with the contacts
outlined (the snapshot with the largest total force).

With ``--port`` or ``--can`` it runs on a real sheet through `host.session.core.Host` (the same
transports as ``capsheet host``): the first ``--learn-s`` seconds must be untouched (rest shape),
then contacts are shown live for ``--duration`` seconds (one line every 0.5 s).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from host.cli.argtypes import usage_error
from host.cli.timing_args import add_timing_args, timing_kwargs
from host.cli.transport_args import add_transport_args, open_transports
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # host.analysis.tactile (and through it the estimator and scipy) is imported where
    # it is used, so that building the CLI's parser stays light
    from host.analysis.tactile import DetectorSettings, Foam, TactileFrame
    from host.analysis.tactile.plot import TrueMark


#: ``--indenter`` choices: the virtual sheet's scripted presses (`_presses`).
INDENTERS = ("sphere-punch", "finger")


def register(subparsers) -> None:
    from host.cli import argtypes as T
    p = subparsers.add_parser(
        "tactile", help="contacts and forces on the sheet wrapped on foam (virtual by default)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = add_transport_args(p, title="source (default: the virtual foam block in-process)")
    src.add_argument("--layout", type=T.existing_file(".csv", ".json", what="a layout file"),
                     help="uid -> link file (real sheet)")
    src.add_argument("--rate", type=T.rate, default=50.0, help="real sheet: SYNC rate, Hz (default 50)")
    src.add_argument("--learn-s", type=T.duration, default=2.0,
                     help="real sheet: untouched period to learn the rest shape, s (default 2)")
    add_timing_args(p)  # real sheet: --ack-timeout-ms --watchdog-ms
    p.add_argument("--calibration", metavar="CAL_JSON", type=T.existing_file(".json", what="a calibration file"),
                   help="apply this calibration (capsheet calibrate) to the readings")
    p.add_argument("--lattice", type=T.lattice, default="14x14", help="joints ROWSxCOLS (default 14x14)")
    p.add_argument("--link-length", type=T.link_length, default=0.01, help="L, metres (default 0.01)")
    foam = p.add_argument_group("foam (the host's force model: F = k sum w A, k = E_oed / h)")
    foam.add_argument("--thickness", type=T.bounded_float(1e-4, 1.0, unit="m", what="a thickness"), default=0.02,
                      help="h, metres (default 0.02)")
    foam.add_argument("--youngs", type=T.bounded_float(1.0, 1e9, unit="Pa"), default=20e3,
                      help="E, Pa (default 20000)")
    foam.add_argument("--poisson", type=T.bounded_float(0.0, 0.49), default=0.25,
                      help="nu, 0 .. 0.49 (default 0.25)")
    virt = p.add_argument_group("virtual sheet")
    virt.add_argument("--body", choices=("block", "cylinder", "sphere"), default="block",
                      help="foam body (default block: a level top face, the paper's Case 1 at rest)")
    virt.add_argument("--indenter", choices=INDENTERS, default="sphere-punch",
                      help="what presses the virtual sheet (default sphere-punch: a 15 mm ball, "
                           "then a 7.5 mm flat punch; finger: a 4 cm finger, then a second "
                           "beside it)")
    virt.add_argument("--noise", type=T.noise, default=1.0, help="reading noise, %% g (default 1)")
    virt.add_argument("--snapshot-rate", type=T.bounded_float(0.0, 1000.0, lo_open=True, unit="per s"), default=8.0,
                      help="snapshots per simulated second (default 8)")
    virt.add_argument("--seed", type=T.seed, default=1, help="noise seed (default 1)")
    p.add_argument("--duration", type=T.bounded_float(0.0, 3600.0, lo_open=True, unit="s"), default=4.0,
                   help="seconds to run (default 4)")
    p.add_argument("--threshold", type=T.positive_float, default=5.0,
                   help="detection threshold in noise sigmas (default 5)")
    p.add_argument("--out", type=T.figure_file, default="out/tactile.png", help="heat map PNG (default out/tactile.png)")
    p.add_argument("-q", "--quiet", action="store_true", help="no status lines")
    from host.cli.record_args import add_record_args
    add_record_args(p)  # --record FILE.mcap (estimates, contacts), --live [PORT]
    p.set_defaults(func=run)


def _status(fr: TactileFrame, L: float) -> str:
    t = "" if fr.t_s is None else f"t={fr.t_s:5.2f}s "
    parts = []
    for c in fr.contacts:
        shape = f"{2e3 * c.axes_m[0]:.0f}x{2e3 * c.axes_m[1]:.0f}mm"
        if np.isfinite(c.angle_std_rad) and c.angle_std_rad < np.pi / 6:
            shape += f"@{np.degrees(c.angle_rad):+.0f}deg"
        parts.append(f"#{c.id} ({c.index[0]:.1f},{c.index[1]:.1f}) {c.force_n:.2f}"
                     f"±{c.force_std_n:.2f}N {shape}" + (" count?" if c.ambiguous else ""))
    line = (f"{t}{len(fr.contacts)} contact(s) total {fr.total_force_n:5.2f} N"
            + (": " + "; ".join(parts) if parts else ""))
    for e in getattr(fr, "events", ()):
        line += f"  [{e.kind} #{e.id}" + ("" if e.t_s is None else f" at {e.t_s:.2f}s") + "]"
    return line


def _presses(which: str, T: float):
    """The scripted presses of ``--indenter`` over a run of ``T`` seconds (surface (u, v), m)."""
    from virtual_sheet.foam import CapsuleIndenter, FlatPunch, Press, SphereIndenter

    if which == "finger":
        ang = 0.5
        e = np.array([np.cos(ang), np.sin(ang)])
        side = 0.025 * np.array([-e[1], e[0]])
        return [Press(CapsuleIndenter(0.008, 0.02, angle_rad=ang), (-0.01, -0.01), 3.0,
                      t_on_s=0.05 * T, t_off_s=0.8 * T, ramp_s=0.05 * T,
                      velocity_mps=tuple(0.01 / T * e)),
                Press(CapsuleIndenter(0.008, 0.02, angle_rad=ang), tuple((-0.01, -0.01) + side),
                      2.0, t_on_s=0.35 * T, t_off_s=0.7 * T, ramp_s=0.05 * T)]
    return [Press(SphereIndenter(0.015), (-0.03, -0.02), 2.0, t_on_s=0.05 * T,
                  t_off_s=0.65 * T, ramp_s=0.1 * T, velocity_mps=(0.01 / T, 0.01 / T)),
            Press(FlatPunch(0.0075), (0.025, 0.02), 1.5, t_on_s=0.25 * T, t_off_s=0.85 * T,
                  ramp_s=0.1 * T)]


def _virtual(args, foam: Foam, settings: DetectorSettings, rows: int, cols: int, outputs):
    from host.snapshots.snapshot import LatticeSnapshot
    from host.analysis.tactile import TactileSensor
    from host.snapshots.feed import corrected
    from virtual_sheet.foam import FoamBlock, FoamCylinder, FoamLayer, FoamScene, FoamSphere
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.sensor import noisy_readings

    L = args.link_length
    layer = FoamLayer(foam.thickness_m, foam.youngs_modulus_pa, foam.poisson)
    body = {"block": lambda: FoamBlock(layer), "cylinder": lambda: FoamCylinder(0.08, layer),
            "sphere": lambda: FoamSphere(0.1, layer)}[args.body]()
    T = args.duration
    scene = FoamScene(body, _presses(args.indenter, T), rows, cols, L)
    rng = np.random.Generator(np.random.MT19937(args.seed))
    n_links = (rows - 1) * cols + rows * (cols - 1)
    # the virtual chips read with the nominal calibration: a calibration file is rebased to it and
    # applied as the host's feed applies it (host.feed.corrected)
    fix = (None if args.cal is None else
           args.cal.rebased(np.zeros((n_links, 3)), np.full((n_links, 3), 1024.0)).apply)
    valid, status = np.ones(n_links, dtype=bool), np.zeros(n_links, dtype=np.uint8)
    valid.setflags(write=False)
    status.setflags(write=False)
    wall0 = time.time()

    def snapshot(k: int, t: float, readings: np.ndarray):
        """The readings as the snapshot a host would hand over, corrected; recorded if asked."""
        readings.setflags(write=False)
        snap = LatticeSnapshot(k, t, wall0 + t, readings, valid, status, True, 0.0)
        return snap if fix is None else corrected(snap, fix)

    r0 = ideal_readings(scene.rest_joints)
    rest = TactileSensor.learn_rest([snapshot(-1, 0.0, noisy_readings(r0, args.noise, rng)).readings
                                     for _ in range(32)], rows, cols, L)
    if not args.quiet:
        print(f"capsheet tactile: virtual {args.body}, {rows}x{cols}, L={L * 100:g} cm, noise "
              f"{args.noise:g} % g; rest learned from 32 untouched snapshots (noise "
              f"{np.median(rest.noise_m) * 1e3:.3f} mm median)", file=sys.stderr)
    sensor = TactileSensor(rest, foam, settings)
    n = max(1, int(round(T * args.snapshot_rate)))
    for k in range(n + 1):
        t = k / args.snapshot_rate
        snap = snapshot(k, t, noisy_readings(ideal_readings(scene.joints(t)), args.noise, rng))
        outputs.snapshot(snap, estimate=False)  # what is estimated is what is recorded
        outputs.emit(snap)  # --publish, --record-ros2: the raw snapshot (a real sheet's host feed sends its own)
        fr = sensor.process(snap.readings, t_s=t)
        yield fr, _true_marks(scene, t, L)


def _true_marks(scene, t: float, L: float) -> list[TrueMark]:
    """The true contacts at ``t`` in lattice indices, with their half-depth footprints (the
    definition of `Contact.axes_m`); angles from the lattice's i direction (the surface's +u is
    the i direction on every virtual body)."""
    from host.analysis.tactile import lattice_index
    from host.analysis.tactile.plot import TrueMark

    contacts = scene.contacts(t)
    if not contacts:
        return []
    fps = {f.index: f for f in scene.footprints(t)}
    out = []
    for c in contacts:
        idx = lattice_index(scene.rest_joints, c.position)
        fp = fps[c.index]
        out.append(TrueMark((float(idx[0]), float(idx[1])), c.force_n,
                            (fp.dent_axes_m[0] / L, fp.dent_axes_m[1] / L), fp.dent_angle_rad))
    return out


def _real(args, rows: int, cols: int):
    """Open the sheet's ports and make the host now (a port that cannot be opened: one line, exit
    1, before anything is written); `_real_frames` then streams from it."""
    from host.session.core import Host, Layout, MismatchError
    from host.transport.ports import TransportError

    try:
        layout = Layout.load(args.layout) if args.layout else None
    except ValueError as exc:
        raise usage_error("capsheet tactile", f"bad --layout: {exc}") from None
    try:
        transports = open_transports(args, prog="capsheet tactile")
    except TransportError as exc:  # a port that does not exist: one line, as capsheet host says it
        raise SystemExit(f"capsheet tactile: {exc}") from None
    try:
        host = Host(transports, f"{rows}x{cols}", rate_hz=args.rate, layout=layout, **timing_kwargs(args))
    except (MismatchError, ValueError) as exc:
        for t in transports:
            t.close()
        raise usage_error("capsheet tactile", str(exc)) from None
    if args.cal is not None:  # before bring-up: it follows the chip calibration the host reads
        host.set_calibration(args.cal)
    return host


def _real_frames(args, host, foam: Foam, settings: DetectorSettings, rows: int, cols: int, outputs):
    from host.analysis.tactile import TactileSensor
    from host.session.core import MismatchError

    outputs.attach(host)  # --record: the raw input, the SYNCs and every snapshot, as emitted
    with host:
        try:
            host.bring_up()
        except MismatchError as exc:  # over capacity (its remedy), layout mismatches
            raise usage_error("capsheet tactile", str(exc)) from None
        outputs.describe(host)
        learn = [s for s in host.snapshots(duration_s=args.learn_s) if s.complete]
        if len(learn) < 2:
            raise SystemExit("capsheet tactile: fewer than 2 complete snapshots while learning "
                             "the rest shape")
        rest = TactileSensor.learn_rest([s.readings for s in learn], rows, cols,
                                        args.link_length)
        sensor = TactileSensor(rest, foam, settings)
        t0 = time.monotonic()
        for s in host.snapshots(duration_s=args.duration):
            if s.valid.sum() < 0.9 * s.valid.size:
                continue
            yield sensor.process(s.readings, valid=s.valid, t_s=s.timestamp - t0), None
        host.stop()


def run(args) -> int:
    from host.analysis.tactile import DetectorSettings, Foam, plot_frame

    rows, cols = args.lattice.rows, args.lattice.cols  # every value was checked by its type (argtypes)
    try:
        foam = Foam(args.thickness, args.youngs, args.poisson)
    except ValueError as exc:
        print(f"capsheet tactile: {exc}", file=sys.stderr)
        return 2
    from host.cli.calibrate import load_calibration_arg
    args.cal = load_calibration_arg(getattr(args, "calibration", None), args.lattice, "capsheet tactile")
    settings = DetectorSettings(k_detect=args.threshold)
    real = bool(args.port or args.can)
    host = _real(args, rows, cols) if real else None  # ports first: a bad one writes nothing
    from host.cli.record_args import SessionOutputs
    from protocol.lattice import Lattice
    outputs = SessionOutputs(args, Lattice(rows, cols), args.link_length, mode="tactile", colour_by="displacement",
                             prog="capsheet tactile")
    source = (_real_frames(args, host, foam, settings, rows, cols, outputs) if real
              else _virtual(args, foam, settings, rows, cols, outputs))
    best, best_truth, last_print = None, None, -1e9
    for k, (fr, truth) in enumerate(source):
        outputs.tactile(k, fr, truth)
        if best is None or fr.total_force_n > best.total_force_n:
            best, best_truth = fr, truth
        if args.quiet:
            continue
        now = time.monotonic()
        if not real or now - last_print >= 0.5:
            line = _status(fr, args.link_length)
            if truth:
                line += "   | true: " + "; ".join(f"({m.index[0]:.1f},{m.index[1]:.1f}) "
                                                  f"{m.force_n:.2f}N" for m in truth)
            print(line)
            last_print = now
    outputs.close()
    if best is None:
        print("capsheet tactile: no snapshot received", file=sys.stderr)
        return 1
    source_name = "real sheet" if real else (f"virtual foam {args.body}, "
                                             f"{args.indenter.replace('-', ' and ')}")
    params = (f"{source_name}, {rows}x{cols}, L = {args.link_length * 100:g} cm"
              + ("" if real else f", noise {args.noise:g} % g")
              + f"; foam h {args.thickness * 1e3:g} mm, E {args.youngs / 1e3:g} kPa, "
                f"nu {args.poisson:g}"
              + (f"; t = {best.t_s:.2f} s" if best.t_s is not None else ""))
    plot_frame(best, args.out, truth=best_truth or None, title=params)
    if not args.quiet:
        print(f"capsheet tactile: heat map written to {args.out}", file=sys.stderr)
    return 0
