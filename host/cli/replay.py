"""``capsheet replay``: play a recording back through the same decoder, aggregator and estimator.

    capsheet replay run.mcap                      # as fast as possible, estimate every snapshot
    capsheet replay run.mcap --speed 1 --live     # real time, into the live 3D view (Foxglove)
    capsheet replay run.log --lattice 14x14       # a candump log (also .asc, .blf)
    capsheet replay run.mcap --record again.mcap  # re-estimated by today's estimator

The recorded raw input (not the recorded snapshots) is decoded again; for a capsheet MCAP the
replayed snapshots are compared with the recorded ones (``snapshots_identical``) and the new
estimates with the recorded ones (``estimate_change_pct_side``: mean joint distance after the rigid
overlay, % of side), so a newer estimator can be judged on old data. A recording of 6/9-axis chips
is shaped as it was live: by the fused estimator, every snapshot in order.

Exit status: 0 when the recording's input made snapshots; 1 when it could not be read (one line:
`host.record.mcap_read`, `host.record.blf_check`), was cut short (without ``--allow-truncated``) or
made no snapshot; 2 for a usage error.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from host.cli.sensor_args import GYRO_DPS, MAG_GAUSS, gyro_range_code, mag_range_code


#: what ``capsheet replay`` and ``estimate`` read
RECORDING_SUFFIXES = (".mcap", ".log", ".asc", ".blf")


def truncated_note(prog: str, path, allow: bool, what: str) -> bool:
    """A recording cut short (its writer killed, a partial copy): say so, once, in one line. Returns
    whether to stop (exit 1): unless ``allow`` (``--allow-truncated``), a partial recording is not
    worked on as if it were whole."""
    if allow:
        print(f"{prog}: {path} was cut short (no MCAP summary: its writer was killed, or the file is a "
              f"partial copy); {what} up to the cut", file=sys.stderr)
        return False
    print(f"{prog}: {path} was cut short (no MCAP summary: its writer was killed, or the file is a partial "
          f"copy); --allow-truncated {what} up to the cut", file=sys.stderr)
    return True


def _no_summary(path) -> bool:
    """An MCAP file (by its magic bytes) without its summary: a killed writer, a partial copy."""
    from host.record.recording import recording_set, snapshot_count
    from protocol.files import open_regular
    try:
        for p in (path if isinstance(path, list) else recording_set(path)):
            with open_regular(p, "a recording") as f:  # a FIFO is not waited on
                if f.read(8) != b"\x89MCAP0\r\n":
                    return False
        return snapshot_count(path) is None
    except (OSError, ValueError):
        return False


def _speed(text: str):
    if text == "max":
        return None
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid speed {text!r} (need 'max' or a number > 0, e.g. 1)") from None
    if not (np.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"invalid speed {text!r} (need 'max' or a number > 0)")
    return v


def register(subparsers) -> None:
    from host.cli import argtypes as T
    from host.cli.record_args import add_record_args

    p = subparsers.add_parser("replay", help="replay a recording (MCAP or CAN log) through decoder, aggregator, estimator",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", type=T.recording_file(*RECORDING_SUFFIXES, what="a recording"), nargs="+",
                   help="capsheet .mcap, or a CAN log (.log candump, .asc, .blf)")
    p.add_argument("--speed", type=_speed, default=None, metavar="1|max",
                   help="'max' (default) as fast as possible, or a factor of real time (1 = as recorded)")
    p.add_argument("--lattice", type=T.lattice, default=None, help="joints ROWSxCOLS (needed for a CAN log)")
    p.add_argument("--link-length", type=T.link_length, default=None,
                   help="L, metres (default: the recording's, or 0.01)")
    p.add_argument("--gyro-range", type=int, choices=GYRO_DPS, default=None, metavar="DPS",
                   help="a CAN log's gyroscope full scale, °/s (default: its CONFIG_IMU's, else 1000)")
    p.add_argument("--mag-range", type=int, choices=MAG_GAUSS, default=None, metavar="GAUSS",
                   help="a CAN log's magnetometer full scale, gauss (default: its CONFIG_IMU's, else 4)")
    p.add_argument("--no-estimate", action="store_true", help="only decode and aggregate")
    p.add_argument("--allow-truncated", action="store_true",
                   help="replay a recording that was cut short (default: say so and exit 1)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (alone on stdout)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    add_record_args(p)
    p.set_defaults(func=run)


def _same_axis(replayed, recorded, k: int) -> bool:
    """A 6/9-axis snapshot's gyro, mag or sample time (docs/protocol.md §16) as recorded: both absent,
    or equal as float32 (NaN where a link had none)."""
    if recorded is None or np.all(np.isnan(recorded[k])):
        return replayed is None or bool(np.all(np.isnan(replayed)))
    if replayed is None:
        return False
    return np.array_equal(np.nan_to_num(np.asarray(replayed, dtype=np.float32), nan=1e30),
                          np.nan_to_num(recorded[k], nan=1e30))


def run(args) -> int:
    from host.analysis.estimator import estimate, overlay_error
    from host.cli.progress import Progress
    from host.cli.record_args import SessionOutputs
    from host.record.replay import Replay

    # one file, a split set by its name, or its files in order (host.record.read)
    src = args.recording[0] if len(args.recording) == 1 else [str(p) for p in args.recording]
    args.recording = args.recording[0] if len(args.recording) == 1 else " + ".join(map(str, args.recording))
    try:
        imu_ranges = None  # a CAN log's ranges, when given (one given: the other's default)
        if args.gyro_range is not None or args.mag_range is not None:
            imu_ranges = (gyro_range_code(args.gyro_range or 1000), mag_range_code(args.mag_range or 4))
        rp = Replay(src, speed=args.speed, lattice=args.lattice, link_length=args.link_length, imu_ranges=imu_ranges)
    except (ValueError, OSError) as exc:
        cut = ""
        if str(args.recording).lower().endswith(".mcap") and _no_summary(src):
            cut = " (it was cut short: no MCAP summary)"
        print(f"capsheet replay: {exc}{cut}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError) and "give the lattice" in str(exc) else 1
    lat, L = rp.lattice, rp.link_length
    rec = rp.recording
    truncated = bool(rec is not None and rec.truncated)
    if truncated and truncated_note("capsheet replay", args.recording, args.allow_truncated, "replays it"):
        return 1
    # by (counter, timestamp): a recording longer than 65536 SYNCs (7.5 min at 145 Hz) holds each counter again
    recorded = ({(int(c), float(t)): k for k, (c, t) in enumerate(zip(rec.counter, rec.timestamp))}
                if rec is not None else {})
    rec_est = ({(int(c), float(t)): k for k, (c, t) in enumerate(zip(rec.estimates["counter"],
                                                                        rec.estimates["timestamp"]))}
               if rec is not None else {})
    att = rec.attachments if rec is not None else {}
    out = SessionOutputs(args, lat, L, mode="replay", prog="capsheet replay",
                         session={"replay_of": str(args.recording),
                                  **{k: v for k, v in (rec.session.items() if rec is not None else ())
                                     if k in ("rate_hz", "sync", "deadline_s", "transports")}},
                         layout=att.get("layout.json"), calibration=att.get("calibration.json"))
    n = identical = compared = est_n = 0
    changes: list[float] = []
    previous = None
    fused = None
    from host.analysis.motion.snapshots import fused_update
    t0 = time.monotonic()
    bar = Progress(rp.n_chunks, "replay", "chunk", quiet=args.quiet)
    last = [0]

    def progress(done: int) -> None:
        if done - last[0] >= 64:
            bar.update(done - last[0])
            last[0] = done
    try:
        rerecord = out.recorder if out.recorder is not None and out.recorder.path is not None else None
        for snap in rp.snapshots(progress=progress, recorder=rerecord):
            n += 1
            k = recorded.get((int(snap.counter), float(snap.timestamp)))
            if k is not None:
                compared += 1
                same = (np.array_equal(snap.valid, rec.valid[k]) and np.array_equal(snap.status, rec.status[k])
                        and np.array_equal(np.nan_to_num(snap.readings.astype(np.float32), nan=1e30),
                                           np.nan_to_num(rec.readings[k], nan=1e30))
                        and all(_same_axis(getattr(snap, a), getattr(rec, a), k)
                                for a in ("gyro", "mag", "sample_time_s")))
                identical += same
            if out.recorder is not None and out.recorder.path is not None:
                out.recorder.snapshot(snap)
            out.emit(snap)  # --publish, --record-ros2: a recording converted
            if args.no_estimate or not snap.valid.any():
                out.imu(snap)  # 6/9-axis chips: the links' IMU messages (--record-ros2), no orientation
                continue
            if snap.gyro is not None:  # 6/9-axis chips: the fused estimator, every snapshot in order (as live)
                if fused is None:
                    from host.analysis.motion import MotionEstimator
                    fused = MotionEstimator(lat.rows, lat.cols, L)
                est = fused_update(fused, snap)
                out.imu(snap, est, fused)  # --publish ros2, --record-ros2: the links' IMU messages
                if est is None:
                    continue
            else:
                est = estimate(snap.readings, lat.rows, lat.cols, L, valid=snap.valid, previous=previous)
                previous = est
            est_n += 1
            j = rec_est.get((int(snap.counter), float(snap.timestamp)))
            if j is not None:
                d = overlay_error(est.joints, rec.estimates["joints"][j].astype(float))
                changes.append(100.0 * float(np.mean(d)) / (L * (max(lat.rows, lat.cols) - 1)))
            if out.wants_estimates:
                out.publish(est, snap)
    except KeyboardInterrupt:
        print("", file=sys.stderr)
    finally:
        bar.update(rp.n_chunks - last[0] if rp.transports and all(t.exhausted for t in rp.transports) else 0)
        bar.close()
        out.close(rp.stats)
    elapsed = time.monotonic() - t0
    result = {"recording": str(args.recording), "lattice": f"{lat.rows}x{lat.cols}", "link_length_m": L,
              "speed": "max" if args.speed is None else args.speed, "snapshots": n,
              "recorded_snapshots": len(rec) if rec is not None else None, "truncated": truncated,
              "snapshots_compared": compared, "snapshots_identical": identical,
              "estimates": est_n, "estimates_compared": len(changes),
              "estimate_change_pct_side_mean": round(float(np.mean(changes)), 5) if changes else None,
              "estimate_change_pct_side_max": round(float(np.max(changes)), 5) if changes else None,
              "recorded_duration_s": round(rp.duration_s, 3), "elapsed_s": round(elapsed, 3),
              # the IMU ranges the records were converted at: the recording's session, or a CAN
              # log's "CONFIG_IMU in the log", "given" (--gyro-range/--mag-range) or "default"
              "imu_ranges_from": rp.imu_ranges_from,
              "aggregator": rp.aggregator.stats.summary(),
              "decode_errors": {t.name: dict(t.stats.errors) for t in rp.transports}}
    if rec is None:  # a CAN log holds frames only
        same = "no recorded snapshots to compare with (a CAN log)"
    elif not len(rec):
        same = "the recording holds no snapshot to compare with"
    elif not compared:
        same = f"none of the {len(rec)} recorded snapshots' counters was replayed"
    else:
        same = f"{identical} of {compared} identical to the recorded ones"
    print(f"capsheet replay: {n} snapshots from {rp.n_chunks} raw chunks ({rp.duration_s:.2f} s recorded) in "
          f"{elapsed:.2f} s; {same}; {est_n} estimated"
          + ("; its raw input made no snapshot: nothing of it could be used" if n == 0 else ""), file=sys.stderr)
    if args.json:
        print(json.dumps(result, indent=1))
    return 0 if n else 1  # a file whose input makes no snapshot is not a replay that worked
