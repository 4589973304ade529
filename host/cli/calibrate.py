"""``capsheet calibrate``: calibrate every chip of a sheet in place, from a few poses of the sheet
clamped flat on a rigid board (docs/calibration.md).

Clamp the sheet flat on a board (i-links along the board's x, j-links along its y, top face up),
then turn the board through the poses it asks for, holding each still until it says "captured".
Static intervals are found automatically (a variance threshold); a pose too close to one already
captured is ignored; each chip is averaged over the still snapshots it is in (lost frames do not
stop a capture). When enough poses are in, it fits every chip's bias, scale and mounting
misalignment jointly, prints each chip's residual and the outliers, and writes the calibration
(JSON). With --write-chips it also writes each chip's offset and sensitivity into the chip with
CAL_WRITE (stored in non-volatile memory where the chip has CAL_STORAGE), reads them back with
CAL_READ and checks them. The misalignment stays in the file: give it to capsheet host / demo /
tactile with --calibration.

    capsheet calibrate --port /dev/ttyUSB0 --baud 12000000 --lattice 14x14 --layout sheet.csv --out cal.json
    capsheet calibrate --can slcan:/dev/ttyACM0 --bitrate 1000000 --lattice 6x6 --out cal.json --write-chips

Without hardware:

    capsheet virtual --shape board --chip-errors realistic --noise 0.3 --layout-out sheet.csv \\
        --symlink /tmp/sheet &
    capsheet calibrate --port /tmp/sheet --baud 12000000 --layout sheet.csv --out cal.json --write-chips

A 6/9-axis sheet (--sensors accel+gyro[+mag]) is calibrated from the same capture: every snapshot
is kept, the gyroscopes' bias, g-sensitivity, scale and cross-axis are fitted from the held poses and
the turns between them, the magnetometers' hard and soft iron from the rotations
(`host.analysis.imu_calibration`, docs/calibration.md); with --write-chips they are written to every
chip with CAL_IMU_WRITE (docs/protocol.md §17: the chip then sends corrected gyroscope and
magnetometer counts), read back with CAL_IMU_READ and checked bit for bit. --field-ut gives the local
field magnitude (without it the magnetometers keep the fitted ellipsoid's mean radius).

The bus must carry the sheet at --rate (checked at bring-up, as capsheet host does): 364 chips at
100 Hz need a 12 Mbaud UART (or --packed, or a lower --rate: poses then take longer to average);
--ignore-capacity streams anyway.

Exit status: 0 calibrated (outliers are reported, not fatal); 1 not enough poses before --timeout,
the fit refused the poses, or a chip's read-back differs from what was written; 1 too when the
gyroscope fit's own residuals say it is wrong — a held pose that was not still (no gyroscope
calibration written) or turns the fitted rates do not carry gravity through (a stalled host or
sheet: only the bias and g-sensitivity written): one line names the figure and its limit, and
the rest of the calibration is still written; 2 usage errors.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

import numpy as np

from host.analysis.calibration import (BOARD_POSES, MIN_POSES, Calibration,
                                       StaticDetector, board_frame_readings, fit_board_poses)
from host.cli.transport_args import add_transport_args, open_transports
from host.transport.ports import TransportError
from protocol.constants import G0
from protocol.lattice import Lattice

__all__ = ["register", "run", "load_calibration_arg", "write_chip_calibration", "write_chip_imu_calibration",
           "PoseCapture", "ImuLog", "hold_needed_s"]

#: a new pose must differ from every captured one by at least this angle, degrees
MIN_POSE_SEPARATION_DEG = 20.0


def hold_needed_s(samples: int, window: int, rate_hz: float) -> float:
    """The shortest hold that captures a pose, seconds: `PoseCapture` judges the chips still once
    its stillness window is full (``window`` snapshots, the last of them the first averaged), then
    averages ``samples`` still snapshots; one snapshot a SYNC at ``rate_hz``. Snapshots that come
    late or lost make it longer.

    >>> round(hold_needed_s(200, 25, 100.0), 6)  # the defaults
    2.24
    """
    return (int(window) - 1 + int(samples)) / float(rate_hz)


def register(subparsers) -> None:
    from host.cli import argtypes as T
    p = subparsers.add_parser("calibrate", help="calibrate every chip in place from poses of the sheet on a board",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_transport_args(p, title="transports (one --port, or one or more --can)")
    p.add_argument("--lattice", type=T.lattice, default="14x14", help="joints ROWSxCOLS (default 14x14)")
    p.add_argument("--layout", type=T.existing_file(".csv", ".json", what="a layout file"),
                   help="uid -> link file (CSV 'uid,link' or JSON; docs/host.md)")
    p.add_argument("--out", required=True, metavar="FILE", type=T.output_file(".json", what="a calibration file"),
                   help="calibration file to write (JSON); checked before any pose is asked for; an existing "
                        "file needs --overwrite")
    T.add_overwrite_arg(p, "calibration files (--out)")
    p.add_argument("--write-chips", action="store_true",
                   help="CAL_WRITE each chip's offset and sensitivity, CAL_READ them back and verify")
    p.add_argument("--poses", type=T.int_range(MIN_POSES, 100), default=len(BOARD_POSES),
                   help=f"poses to capture, >= {MIN_POSES} (default {len(BOARD_POSES)}: docs/calibration.md)")
    p.add_argument("--samples", type=T.int_range(1, 100_000), default=200,
                   help="snapshots averaged per pose (default 200: 2 s at 100 Hz)")
    p.add_argument("--rate", type=T.rate, default=100.0, help="SYNC rate, Hz (default 100)")
    p.add_argument("--packed", action="store_true",
                   help="the gateway packs SNAPSHOT frames: check the bus capacity for those")
    p.add_argument("--ignore-capacity", action="store_true",
                   help="stream even when the traffic exceeds a bus's capacity (default: refuse, exit 2; a lower "
                        "--rate only makes each pose take longer)")
    p.add_argument("--window", type=T.int_range(2, 10_000), default=25,
                   help="snapshots in the stillness window (default 25)")
    p.add_argument("--still-threshold", type=T.positive_float, default=0.098, metavar="M/S2",
                   help="a chip is still when its readings' standard deviation over the window is below "
                        "this (default 0.098 m/s^2 = 1 %% g)")
    p.add_argument("--non-orthogonality", action="store_true",
                   help="also fit 3 axis non-orthogonality terms per chip (kept in the file, like the misalignment)")
    p.add_argument("--gravity", type=T.bounded_float(1.0, 30.0, unit="m/s^2"), default=G0, metavar="M/S2",
                   help=f"local gravity (default standard gravity {G0}); sets the common scale")
    p.add_argument("--timeout", type=T.duration, default=600.0, help="give up after this many seconds (default 600)")
    p.add_argument("--discover-s", type=T.bounded_float(0.0, 60.0, lo_open=True, unit="s"), default=0.5,
                   help="discovery window per round (s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout (messages on stderr)")
    p.add_argument("-q", "--quiet", action="store_true", help="no live indicator")
    p.add_argument("--field-ut", type=T.bounded_float(1.0, 1000.0, unit="µT"), default=None, metavar="UT",
                   help="local magnetic field magnitude, µT (a geomagnetic model gives it; default: the fitted "
                        "ellipsoids' mean radius)")
    from host.analysis.imu_calibration import TURN_MAX_RESIDUAL_RAD
    p.add_argument("--max-turn-residual-deg", type=T.bounded_float(0.0, 90.0, unit="°"),
                   default=float(np.degrees(TURN_MAX_RESIDUAL_RAD)), metavar="DEG",
                   help="6/9-axis chips: fit the gyroscopes' scale and cross-axis only when the turns, "
                        "integrated with them, carry gravity to where it was seen within this, degrees "
                        f"(default {np.degrees(TURN_MAX_RESIDUAL_RAD):g}: about 0.3 %% of scale; above it the "
                        "command keeps bias and g-sensitivity, leaves the chips' matrix and exits 1)")
    from host.cli.sensor_args import add_sensor_args
    add_sensor_args(p)  # --sensors, --gyro-range, --mag-range
    from host.cli.timing_args import add_timing_args
    add_timing_args(p)  # --ack-timeout-ms --watchdog-ms
    p.set_defaults(func=run)


# --------------------------------------------------------------------------------------------
# Helpers other commands use (--calibration)
# --------------------------------------------------------------------------------------------

def load_calibration_arg(path: str | None, lattice, prog: str) -> Calibration | None:
    """``--calibration FILE`` -> `Calibration` for ``lattice`` (``Lattice`` or "RxC"), or exit 2
    with a one-line message (unreadable, malformed, or another lattice's file)."""
    if not path:
        return None
    def usage(text: str):
        print(f"{prog}: {text}", file=sys.stderr)
        return SystemExit(2)
    try:
        cal = Calibration.load(path)
    except (OSError, ValueError) as exc:
        raise usage(f"--calibration: {exc}") from None
    try:
        lat = lattice if isinstance(lattice, Lattice) else Lattice.parse(str(lattice))
        rows, cols = lat.rows, lat.cols
    except ValueError:
        raise usage(f"--lattice {lattice!r}: expected ROWSxCOLS") from None
    if (cal.rows, cal.cols) != (rows, cols):
        raise usage(f"--calibration {path} is for a {cal.rows}x{cal.cols} lattice, not {rows}x{cols}")
    return cal


def _store_flag(rec) -> int:
    """CAL_WRITE's and CAL_IMU_WRITE's store flag for a chip: 1 where its INFO announces CAL_STORAGE."""
    from protocol.messages import Capability
    return 1 if rec.info is not None and rec.info.capabilities & Capability.CAL_STORAGE else 0


def _write_rounds(host, chips: dict, command: int, steps) -> set[int]:
    """Per step ``(what, {key: message})`` one command round (`Host.command_round`, with its
    retries): every chip of the step is sent its message, its ACK or NACK of ``command`` collected.
    Returns the links of the chips that NACKed or never answered, in any step."""
    from protocol.messages import Ack, Nack

    def match(bus, msg):
        if isinstance(msg, (Ack, Nack)) and msg.command == command:
            return (bus, msg.node)
        return None

    refused: set[int] = set()
    for what, msgs in steps:
        answers, missing = host.command_round(msgs, lambda key, _attempt, msgs=msgs: [(key[0], msgs[key])],
                                              match, what)
        refused |= {chips[k].link for k, m in answers.items() if not isinstance(m, Ack)}
        refused |= {chips[k].link for k in missing}
    return refused


def write_chip_calibration(host, offset_counts: np.ndarray, sensitivity: np.ndarray) -> dict:
    """CAL_WRITE every assigned chip's three axes (chips must be IDLE), then CAL_READ them back.

    ``offset_counts`` and ``sensitivity`` are ±2 g counts, (n_links, 3). The store flag is set for
    chips whose INFO announces CAL_STORAGE. Returns ``{"written", "verified", "refused", "mismatch"}``
    (link lists; mismatch entries name link, axis, written and read values).
    """
    from protocol.messages import CalWrite, MsgType

    q4 = np.clip(np.rint(np.asarray(offset_counts) * 16.0), -32768, 32767).astype(int)
    sens = np.asarray(sensitivity, dtype=np.float32)
    chips = host.chips_by_node()
    refused = _write_rounds(host, chips, MsgType.CAL_WRITE, (
        (f"CAL_WRITE axis {axis}",
         {key: CalWrite(key[1], axis=axis, flags=_store_flag(rec), offset_q4=int(q4[rec.link, axis]),
                        sensitivity=float(sens[rec.link, axis])) for key, rec in chips.items()})
        for axis in range(3)))
    host.read_calibration()
    scale = float(1 << int(host.range_code))
    verified, mismatch = [], []
    for rec in chips.values():
        k = rec.link
        bad = False
        for axis in range(3):
            got_q4 = int(round(float(rec.offset[axis]) * 16.0 * scale))
            got_s = np.float32(float(rec.sensitivity[axis]) * scale)
            if got_q4 != q4[k, axis] or got_s != sens[k, axis]:
                bad = True
                mismatch.append({"link": k, "axis": "xyz"[axis], "written": [int(q4[k, axis]), float(sens[k, axis])],
                                 "read": [got_q4, float(got_s)]})
        if not bad and rec.calibrated:
            verified.append(k)
    return {"written": sorted(rec.link for rec in chips.values() if rec.link not in refused),
            "verified": sorted(verified), "refused": sorted(refused), "mismatch": mismatch}


def write_chip_imu_calibration(host, blocks: list[dict]) -> dict:
    """CAL_IMU_WRITE every element of ``blocks`` (per link ``{block: [values]}``, `chip_imu_blocks`)
    to every assigned chip (IDLE), stored where the chip has CAL_STORAGE, then CAL_IMU_READ them back
    (`Host.read_imu_calibration`) and compare bit for bit. Returns ``{"written", "verified",
    "refused", "mismatch"}`` (link lists; mismatch entries name link, block, index, written, read)."""
    from protocol.messages import CalImuWrite, MsgType

    chips = host.chips_by_node()
    want = {key: [(b, i, float(np.float32(v))) for b, vals in sorted(blocks[rec.link].items())
                  for i, v in enumerate(vals)] for key, rec in chips.items()}
    refused = _write_rounds(host, chips, MsgType.CAL_IMU_WRITE, (
        (f"CAL_IMU_WRITE element {step}",
         {key: CalImuWrite(key[1], *want[key][step][:2], _store_flag(rec), 0, want[key][step][2])
          for key, rec in chips.items() if step < len(want[key])})
        for step in range(max((len(w) for w in want.values()), default=0))))
    host.read_imu_calibration()
    verified, mismatch = [], []
    for key, rec in chips.items():
        bad = False
        for b, i, v in want[key]:
            got = rec.imu_cal.get((b, i))
            if got is None or np.float32(got[0]).tobytes() != np.float32(v).tobytes():
                bad = True
                mismatch.append({"link": rec.link, "block": b, "index": i, "written": v,
                                 "read": None if got is None else got[0]})
        if not bad and want[key]:
            verified.append(rec.link)
    return {"written": sorted(rec.link for k, rec in chips.items() if want[k] and rec.link not in refused),
            "verified": sorted(verified), "refused": sorted(refused), "mismatch": mismatch}


def _current_imu_blocks(host, n_links: int) -> list[dict]:
    """What every link's chip applies now (read at bring-up), ``{block: [values]}``; nominal where
    a chip did not answer an element."""
    from protocol.imu_units import nominal_imu_cal

    out = [nominal_imu_cal() for _ in range(n_links)]
    for rec in host.chips_by_node().values():
        for (b, i), (v, _stored) in rec.imu_cal.items():
            out[rec.link][b][i] = v
    return out


class ImuLog:
    """Every snapshot of a 6/9-axis capture, for `host.analysis.imu_calibration.fit_capture`: each
    link's sample instant, specific force, rates, field; a link missing from a snapshot repeats its
    previous reading and that reading's instant (the fit takes no NaN); snapshots before every link
    was heard once are left out.

    A link's instant is the one its chip latched the reading at: the snapshot's SYNC time plus the
    record's ``time_us`` (``sample_time_s``; docs/protocol.md §16.1 — the SYNC time alone where the
    chip does not know it). The turns are integrated over these, not over the SYNC times: a SYNC
    the host sent late, or a chip whose gyroscope converts on its own clock, moves the SYNC time
    but not the instant the rate was measured at. An instant before the same link's previous one
    (a ``time_us`` that cannot be) is taken as that previous one, and counted (``reordered``)."""

    def __init__(self, mag: bool) -> None:
        self.mag = mag
        self.t: list[np.ndarray] = []  #: per snapshot, each link's sample instant (n_links,)
        self.a: list[np.ndarray] = []
        self.g: list[np.ndarray] = []
        self.m: list[np.ndarray] = []
        self._last: list[np.ndarray] | None = None
        self.filled = 0  #: link readings repeated for a missing record
        self.reordered = 0  #: link instants before the same link's previous one, taken as that one

    def add(self, snap) -> None:
        if snap.gyro is None or (self.mag and snap.mag is None):
            return
        cur = [np.asarray(snap.readings, dtype=float), np.asarray(snap.gyro, dtype=float)]
        if self.mag:
            cur.append(np.asarray(snap.mag, dtype=float))
        ok = np.ones(cur[0].shape[0], dtype=bool)
        for x in cur:
            ok &= np.isfinite(x).all(axis=1)
        st = getattr(snap, "sample_time_s", None)
        dt = np.zeros(ok.shape) if st is None else np.asarray(st, dtype=float)
        t = float(snap.timestamp) + np.where(np.isfinite(dt), dt, 0.0)
        cur.append(t)
        if self._last is None:
            if not ok.all():
                return
        else:
            self.filled += int((~ok).sum())
            cur = [np.where(ok[:, None], x, last) if x.ndim == 2 else np.where(ok, x, last)
                   for x, last in zip(cur, self._last)]
            back = cur[-1] < self._last[-1]
            self.reordered += int(back.sum())
            cur[-1] = np.where(back, self._last[-1], cur[-1])
        self._last = cur
        self.t.append(cur[-1])
        self.a.append(cur[0])
        self.g.append(cur[1])
        if self.mag:
            self.m.append(cur[2])

    def arrays(self):
        """``(t (N, n_links), accel (N, n_links, 3), gyro, mag or None)``."""
        return (np.array(self.t), np.array(self.a), np.array(self.g), np.array(self.m) if self.mag else None)


# --------------------------------------------------------------------------------------------
# Capturing poses (sans-I/O: snapshots in, progress out)
# --------------------------------------------------------------------------------------------

class PoseCapture:
    """Collects static poses from a stream of snapshots.

    `update` takes one snapshot's readings (m/s², (n_links, 3); NaN or ``valid`` False for a
    missing link) and returns what happened: ``"moving"``, ``"holding"`` (static, averaging),
    ``"duplicate"`` (static, but within `MIN_POSE_SEPARATION_DEG` of a captured pose),
    ``"captured"`` (every link has ``samples`` still samples averaged) or ``"incomplete"`` (no
    link in the snapshot). A link missing from some snapshots (a lost frame) is averaged over the
    snapshots it is in, and judged still on the windows it is in.
    """

    def __init__(self, rows: int, cols: int, *, samples: int = 200, window: int = 25,
                 threshold_mps2: float = 0.098) -> None:
        if samples < 1:
            raise ValueError(f"Invalid samples: {samples!r} (need >= 1)")
        self.rows, self.cols = rows, cols
        n = (rows - 1) * cols + rows * (cols - 1)
        self.detector = StaticDetector(n, window=window, threshold_mps2=threshold_mps2, quantile=1.0)
        self.samples = int(samples)
        self.poses: list[np.ndarray] = []  #: averaged readings of each captured pose, (n_links, 3)
        self.directions: list[np.ndarray] = []  #: each captured pose's gravity direction, board frame
        self._sum = np.zeros((n, 3))
        self._count = np.zeros(n, dtype=int)

    @property
    def progress(self) -> float:
        """Fraction of the samples the least-sampled link has."""
        return float(self._count.min()) / self.samples

    def _restart(self) -> None:
        self._sum[:] = 0.0
        self._count[:] = 0

    def _direction(self, readings: np.ndarray) -> np.ndarray:
        m = np.nanmean(board_frame_readings(readings, self.rows, self.cols), axis=0)
        return m / np.linalg.norm(m)

    def update(self, readings: np.ndarray, valid: np.ndarray | None = None) -> str:
        r = np.asarray(readings, dtype=float)
        ok = np.isfinite(r).all(axis=1)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        if not ok.any():
            return "incomplete"
        r = np.where(ok[:, None], r, np.nan)
        if not self.detector.update(r):
            self._restart()
            return "moving"
        if not self._count.any():
            u = self._direction(r)
            cos_min = np.cos(np.radians(MIN_POSE_SEPARATION_DEG))
            if any(float(u @ d) > cos_min for d in self.directions):
                return "duplicate"
        self._sum[ok] += r[ok]
        self._count[ok] += 1
        if self._count.min() < self.samples:
            return "holding"
        mean = self._sum / self._count[:, None]
        self._restart()
        self.poses.append(mean)
        self.directions.append(self._direction(mean))
        return "captured"

    def next_pose(self) -> tuple[str, str]:
        """(name, instruction) of the first suggested pose not yet covered."""
        cos_min = np.cos(np.radians(MIN_POSE_SEPARATION_DEG))
        for name, what, u in BOARD_POSES:
            if not any(float(np.asarray(u) @ d) > cos_min for d in self.directions):
                return name, what
        return "any other", "any orientation not yet captured"

    def nearest_name(self, u: np.ndarray) -> str:
        return max(BOARD_POSES, key=lambda p: float(np.asarray(p[2]) @ u))[0]


# --------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------

def _say(args, text: str) -> None:
    print(f"capsheet calibrate: {text}", file=sys.stderr, flush=True)


def _bar(frac: float, width: int = 20) -> str:
    k = int(round(max(0.0, min(1.0, frac)) * width))
    return "#" * k + "." * (width - k)


def _next_snapshot(host, timeout_s: float):
    """The next snapshot, or None after ``timeout_s`` of the host's clock: a host on a simulated
    clock (manual mode) runs the world while it waits."""
    if not host.manual:
        return host.get(timeout_s)
    end = host.now() + timeout_s
    while True:
        snap = host.get(0)
        if snap is not None or host.now() >= end:
            return snap
        host.idle(host.tick_s)


def _capture(host, args, cap: PoseCapture, log: ImuLog | None = None) -> bool:
    from host.cli.progress import LiveLine

    # a terminal: one line redrawn; a pipe or log: a line per new state, else every 5 s
    live = LiveLine(quiet=args.quiet, every_s=5.0)
    t_end = host.now() + args.timeout
    while len(cap.poses) < args.poses:
        if host.now() > t_end:
            live.end()
            _say(args, f"timed out after {args.timeout:g} s with {len(cap.poses)} of {args.poses} poses")
            return False
        snap = _next_snapshot(host, 0.5)
        if snap is None:
            continue
        if log is not None:
            log.add(snap)
        what = cap.update(snap.readings, snap.valid)
        if what == "captured":
            u = cap.directions[-1]
            live.end()
            _say(args, f"captured pose {len(cap.poses)}/{args.poses} (nearest: {cap.nearest_name(u)}; "
                       f"gravity in the board frame {np.round(u, 3).tolist()})")
            continue
        key = (len(cap.poses), what)
        if live.due(key):
            name, instruction = cap.next_pose()
            shown = {"moving": "moving ... set the board down and hold still",
                     "holding": f"HOLD STILL [{_bar(cap.progress)}] {100 * cap.progress:3.0f} %",
                     "duplicate": "still, but this pose is already captured: turn the board",
                     "incomplete": "waiting for the chips"}[what]
            live.show(f"pose {len(cap.poses) + 1}/{args.poses} next: {name} ({instruction}) | {shown}", key)
    live.end()
    return True


def _chip_table(cal: Calibration) -> list[dict]:
    return [{"link": k, "rms_mg": round(float(cal.chip_rms[k]) / G0 * 1e3, 3),
             "bias_mg": np.round(cal.bias[k] / G0 * 1e3, 2).tolist(),
             "scale_pct": np.round((cal.scale[k] - 1) * 100, 3).tolist(),
             "misalignment_deg": np.round(np.degrees(cal.misalignment[k]), 3).tolist(),
             "outlier": k in cal.outliers} for k in range(cal.n_links)]


def _imu_summary(imu_cal, log: ImuLog) -> dict:
    out = {"snapshots": len(log.t), "held_poses": len(imu_cal.segments), "readings_repeated": log.filled,
           "sample_times_reordered": log.reordered}
    if imu_cal.gyro is not None or imu_cal.gyro_refused:
        # the figures judged by are those of the whole fit, kept or not
        judged = imu_cal.gyro_rejected if imu_cal.gyro_rejected is not None else imu_cal.gyro
        out["gyro_fitted"] = ("none" if imu_cal.gyro is None else
                              "bias and g-sensitivity" if not imu_cal.gyro.scale_fitted else "all")
        if imu_cal.gyro is not None:
            out["gyro_bias_dps_max"] = round(float(np.degrees(np.abs(imu_cal.gyro.bias_rps).max())), 4)
        out["gyro_rest_residual_dps_max"] = round(float(np.degrees(judged.rest_residual_rps.max())), 4)
        out["gyro_rest_residual_dps_limit"] = round(float(np.degrees(imu_cal.max_rest_residual_rps)), 4)
        if judged.scale_fitted:
            out["gyro_turn_residual_max"] = round(float(judged.turn_residual.max()), 5)
            out["gyro_turn_residual_deg_max"] = round(float(np.degrees(judged.turn_residual.max())), 3)
            out["gyro_turn_residual_deg_limit"] = round(float(np.degrees(imu_cal.max_turn_residual_rad)), 3)
            out["gyro_turns_used"] = judged.turns_used
            out["gyro_turns_dropped"] = judged.turns_dropped  # a gap in their samples, or rejected
            out["gyro_turns_rejected"] = judged.turns_rejected  # far off the others: their instants were wrong
        if imu_cal.gyro_refused:
            out["gyro_refused"] = imu_cal.gyro_refused
    if imu_cal.mag is not None:
        ok = np.isfinite(imu_cal.mag.residual_t)
        out["mag_failed_chips"] = int((~ok).sum())
        out["mag_residual_ut_max"] = round(float(1e6 * imu_cal.mag.residual_t[ok].max()), 3) if ok.any() else None
    return out


def _imu_line(s: dict) -> str:
    """`_imu_summary` as a person reads it (``--json`` carries the same figures by name)."""
    parts = []
    if "gyro_fitted" in s:
        g = {"all": "gyroscope bias, g-sensitivity, scale and cross-axis fitted",
             "none": "gyroscope not fitted"}.get(s["gyro_fitted"], f"gyroscope {s['gyro_fitted']} fitted")
        if "gyro_bias_dps_max" in s:
            g += f", bias up to {s['gyro_bias_dps_max']:g} °/s"
        g += (f"; rest residual up to {s['gyro_rest_residual_dps_max']:g} °/s "
              f"(limit {s['gyro_rest_residual_dps_limit']:g})")
        if "gyro_turn_residual_deg_max" in s:
            g += (f"; turn residual up to {s['gyro_turn_residual_deg_max']:g}° "
                  f"(limit {s['gyro_turn_residual_deg_limit']:g}°) over {s['gyro_turns_used']} turns, "
                  f"{s['gyro_turns_dropped']} dropped, {s['gyro_turns_rejected']} rejected")
        parts.append(g)
    if "mag_failed_chips" in s:
        m = s["mag_residual_ut_max"]
        parts.append(f"magnetometer residual up to {'n/a' if m is None else f'{m:g}'} µT, "
                     f"{s['mag_failed_chips']} chips failed")
    if s["readings_repeated"] or s["sample_times_reordered"]:
        parts.append(f"{s['readings_repeated']} readings repeated, {s['sample_times_reordered']} sample "
                     "times reordered")
    return "; ".join(parts) or "nothing fitted"


def run(args, *, clock=None, driver=None) -> int:
    """The command. ``clock`` and ``driver`` run its host on a simulated clock (`Host`'s manual
    mode; tests): the capture's ``--timeout`` is then that clock's too."""
    from host.session.core import Host, Layout

    from host.session.core import MismatchError

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    rows, cols = args.lattice.rows, args.lattice.cols  # every value was checked by its type (argtypes)
    cap = PoseCapture(rows, cols, samples=args.samples, window=args.window, threshold_mps2=args.still_threshold)
    try:
        layout = Layout.load(args.layout) if args.layout else None
    except (OSError, ValueError) as exc:
        print(f"capsheet calibrate: --layout: {exc}", file=sys.stderr)
        return 2
    try:
        transports = open_transports(args, prog="capsheet calibrate")
    except TransportError as exc:
        print(f"capsheet calibrate: {exc}", file=sys.stderr)
        return 1
    try:
        from host.cli.timing_args import timing_kwargs
        host = Host(transports, args.lattice, layout=layout, rate_hz=args.rate, clock=clock, driver=driver,
                    **timing_kwargs(args))
        from host.cli.sensor_args import imu_config
        host.imu_config = imu_config(args)
    except (MismatchError, ValueError) as exc:
        for t in transports:
            t.close()
        print(f"capsheet calibrate: {exc}", file=sys.stderr)
        return 2
    result: dict = {}
    with host:
        try:
            summary = host.bring_up(args.discover_s, capacity="warn" if args.ignore_capacity else "refuse",
                                    packed=args.packed)
        except MismatchError as exc:  # over capacity (the remedy fits what is set), layout mismatches
            print(f"capsheet calibrate: {exc}" + (" (or --ignore-capacity)" if "capacity" in str(exc) else ""),
                  file=sys.stderr)
            return 2
        if summary["discovered"] == 0:
            _say(args, f"no chip answered on {', '.join(t.name for t in transports)} (is the sheet powered and "
                       f"the port right?)")
            return 1
        if host.imu_config is not None:  # the gyroscopes (and magnetometers) asked for must be there
            from protocol.messages import Capability
            need = Capability.GYRO | (Capability.MAG if args.sensors.endswith("mag") else 0)
            missing, lacking = 0, []
            for rec in host.chips_by_node().values():
                gap = need & ~(rec.info.capabilities if rec.info is not None else 0)
                if gap:
                    missing |= gap
                    lacking.append(rec.link)
            lacking.sort()
            if lacking:
                what = " and ".join(n for bit, n in ((Capability.GYRO, "gyroscope"), (Capability.MAG, "magnetometer"))
                                    if missing & bit)
                _say(args, f"--sensors {args.sensors}: {len(lacking)} of {summary['assigned']} chips announce no "
                           f"{what} (INFO capabilities; links {', '.join(map(str, lacking[:8]))}"
                           f"{' ...' if len(lacking) > 8 else ''}): calibrate them with --sensors accel")
                return 1
        _say(args, f"{summary['discovered']} chips found, {summary['assigned']} assigned, "
                   f"{summary['started']} streaming; clamp the sheet flat on the board and follow the poses, "
                   f"holding each still for at least {hold_needed_s(args.samples, args.window, args.rate):.1f} s")
        if summary["assigned"] < host.lattice.n_links:
            _say(args, f"only {summary['assigned']} of {host.lattice.n_links} links have a chip: "
                       "every link is needed")
            return 1
        ref_off, ref_sens = host.chip_calibration()
        log = ImuLog(mag=args.sensors.endswith("mag")) if host.imu_config is not None else None
        current_imu = _current_imu_blocks(host, host.lattice.n_links) if log is not None else None
        try:
            done = _capture(host, args, cap, log)
        except KeyboardInterrupt:
            print(file=sys.stderr)
            _say(args, "interrupted")
            return 130
        host.stop()
        if not done:
            return 1
        try:
            cal = fit_board_poses(np.array(cap.poses), rows, cols, reference_offset_counts=ref_off,
                                  reference_sensitivity=ref_sens, gravity_mps2=args.gravity,
                                  non_orthogonality=args.non_orthogonality)
        except ValueError as exc:
            _say(args, f"fit refused: {exc}")
            return 1
        imu_cal = None
        if log is not None:
            from host.analysis.imu_calibration import fit_capture
            t_s, a, g, m = log.arrays()
            try:
                imu_cal = fit_capture(t_s, a, rows, cols, g, m, window=args.window, threshold_mps2=args.still_threshold,
                                      field_t=None if args.field_ut is None else args.field_ut * 1e-6,
                                      min_hold_samples=max(4, args.samples // 2),
                                      max_turn_residual_rad=float(np.radians(args.max_turn_residual_deg)))
            except ValueError as exc:
                _say(args, f"gyroscope/magnetometer fit refused: {exc}")
                return 1
        table = _chip_table(cal)
        result = {"poses": len(cap.poses), "samples_per_pose": args.samples,
                  "residual_rms_mg": round(cal.residual_rms / G0 * 1e3, 4),
                  "outliers": list(cal.outliers), "out": args.out, "chips": table}
        out = sys.stderr if args.json else sys.stdout
        if not args.json:
            print("link  rms[mg]  bias x/y/z [mg]          scale-1 x/y/z [%]        misalignment x/y/z [deg]", file=out)
            for row in table:
                print(f"{row['link']:4d}  {row['rms_mg']:7.3f}  "
                      + " ".join(f"{v:7.2f}" for v in row["bias_mg"]) + "  "
                      + " ".join(f"{v:7.3f}" for v in row["scale_pct"]) + "  "
                      + " ".join(f"{v:7.3f}" for v in row["misalignment_deg"])
                      + ("  OUTLIER" if row["outlier"] else ""), file=out)
        _say(args, f"fit of {cal.n_links} chips over {len(cap.poses)} poses: residual RMS "
                   f"{result['residual_rms_mg']:.3f} mg; outliers: "
                   f"{', '.join(map(str, cal.outliers)) if cal.outliers else 'none'}")
        if imu_cal is not None:
            result["imu"] = _imu_summary(imu_cal, log)
            _say(args, f"gyroscope{'/magnetometer' if imu_cal.mag is not None else ''} fit over {len(log.t)} "
                       f"snapshots, {len(imu_cal.segments)} held poses: {_imu_line(result['imu'])}")
        status = 0
        refused = ""
        if imu_cal is not None and imu_cal.gyro_refused:
            # the fit's own residuals say it is wrong: not written (the parts they vouch for are);
            # said last, where it is seen
            refused = imu_cal.gyro_refused + ("" if not args.write_chips else
                                              "; the chips keep their gyroscope calibration"
                                              if imu_cal.gyro is None else "; the chips keep their gyroscope matrix")
            status = 1
        if args.write_chips and imu_cal is not None and (imu_cal.gyro is not None or imu_cal.mag is not None):
            from host.analysis.imu_calibration import chip_imu_blocks
            blocks = chip_imu_blocks(imu_cal.gyro, imu_cal.mag, imu_cal.accel, ref_off, ref_sens, current_imu)
            w = write_chip_imu_calibration(host, blocks)
            result["write_chips_imu"] = w
            _say(args, f"CAL_IMU_WRITE: {len(w['written'])} chips written, {len(w['verified'])} read back "
                       f"and verified, {len(w['refused'])} refused, {len(w['mismatch'])} element mismatches")
            if w["refused"] or w["mismatch"] or len(w["verified"]) < cal.n_links:
                status = 1
        if args.write_chips:
            off, sens = cal.chip_calibration()
            w = write_chip_calibration(host, off, sens)
            result["write_chips"] = w
            _say(args, f"CAL_WRITE: {len(w['written'])} chips written, {len(w['verified'])} read back "
                       f"and verified, {len(w['refused'])} refused, {len(w['mismatch'])} axis mismatches")
            if w["refused"] or w["mismatch"] or len(w["verified"]) < cal.n_links:
                status = 1
            cal = cal.rebased(*host.chip_calibration())  # the file now describes the written chips
        try:
            cal.save(args.out)
        except OSError as exc:
            _say(args, f"cannot write {args.out}: {exc}")
            return 1
        _say(args, f"wrote {args.out}")
        if refused:
            _say(args, refused)
    if args.json:
        print(json.dumps(result, indent=1))
    return status
