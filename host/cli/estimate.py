"""``capsheet estimate``: estimate every snapshot of a recording offline, in batches, on all cores.

    capsheet estimate run.mcap --out joints.npz            # numpy arrays
    capsheet estimate run.mcap --out shapes.mcap --png     # MCAP (Foxglove 3D) and a figure
    capsheet estimate run.log --lattice 14x14 --out joints.npz   # a CAN log: replayed first
    capsheet estimate --subscribe --worker 0/2              # a worker: sheets published on Zenoh, live

With ``--subscribe`` it is an estimate worker instead (docs/distribution.md "Estimate workers"): it
takes the snapshots hosts publish with ``capsheet host --publish zenoh`` (``capsheet/<sheet>/snapshot``),
asks each sheet's ``capsheet/<sheet>/info`` for its lattice and link length, estimates every snapshot
in order and publishes one estimate for each under ``capsheet/<sheet>/estimate``. ``--sheets`` names
the sheets it takes, ``--worker I/N`` shares them among N workers without coordination; lost
snapshots are counted from the SYNC counters, and a summary per sheet is printed at the end.

The recorded snapshots are estimated (a CAN log, or ``--from-raw``, is first replayed through the
decoder and aggregator, `host.record.replay`). Snapshots are read in batches of ``--batch`` (each warm-
starts from its own first snapshot, as a live run does from its previous one) and each batch goes
to one of ``--jobs`` processes as soon as it is read. ``joints.npz`` holds ``counter`` (n,), ``timestamp`` (n,) s, ``joints``
(n, rows, cols, 3) m, ``residual`` (n,), ``valid`` (n, n_links), ``link_length_m``, ``lattice``,
and with ``--uncertainty`` ``yaw_std`` (n, n_links) rad and ``joint_std`` (n, rows, cols) m (also in
the MCAP's estimates). The uncertainty is sampled (200 solves per snapshot, tens of times the estimate
itself), so it is off by default: without it a 14x14 recording is estimated many times faster than
real time, with it slower than real time.

A recording of 6/9-axis chips (``capsheet host --sensors accel+gyro`` or ``accel+gyro+mag``,
docs/protocol.md §16) carries every link's gyroscope (and magnetometer) and sample time: ``--method
auto`` (the default) then shapes it with the fused estimator (`host.analysis.motion.MotionEstimator`,
docs/estimator.md §8) as ``capsheet demo --sensors ...`` does live: every snapshot in order, each
link at its own sample time, the gyroscopes the process model (the magnetometers, when recorded,
the heading). It carries its state from snapshot to snapshot, so it runs in one process whatever
``--jobs`` says (no worker is started for it); ``residual`` is then eq. (8) of its directions and normals. An accelerometer
recording is estimated as before (``auto`` is ``global`` there).

A recording is read within bounds (`host.record.mcap_read`: decompressed sizes, the declared lattice,
every record's lengths): one that cannot be read, or of which no snapshot can be estimated, is one
line on stderr and exit 1, nothing written; exit 2 for a usage error; 0 when estimates were written.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def register(subparsers) -> None:
    from host.cli import argtypes as T
    from host.cli.replay import RECORDING_SUFFIXES
    p = subparsers.add_parser("estimate", help="estimate a recording offline (batched, all cores) to .npz or .mcap",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", type=T.recording_file(*RECORDING_SUFFIXES, what="a recording"), nargs="*",
                   help="capsheet .mcap, or a CAN log (.log, .asc, .blf); none with --subscribe")
    p.add_argument("--out", type=T.output_file(".npz", ".mcap", what="an output file"),
                   help="joints.npz or shapes.mcap (an existing file needs --overwrite); required with a recording")
    T.add_overwrite_arg(p, "output files (--out)")
    p.add_argument("--png", nargs="?", const="", default=None, metavar="FILE", type=T.figure_file,
                   help="also draw the run (default: --out with .png)")
    p.add_argument("--allow-truncated", action="store_true",
                   help="estimate a recording that was cut short (default: say so and exit 1)")
    p.add_argument("--lattice", type=T.lattice, default=None, help="joints ROWSxCOLS (needed for a CAN log)")
    p.add_argument("--link-length", type=T.link_length, default=None,
                   help="L, metres (default: the recording's, or 0.01)")
    p.add_argument("--from-raw", action="store_true", help="replay the raw input instead of the recorded snapshots")
    p.add_argument("--method", choices=METHODS, default="auto",
                   help="auto (default): fused when the recording carries gyroscopes (6/9-axis chips), else global. "
                        "fused: the lattice's loops with the gyroscopes (and magnetometers when recorded), every "
                        "snapshot in order, one process: right while the sheet moves, and it needs the gyroscopes. "
                        "global / paper: the accelerometers alone, each snapshot on its own, batched over --jobs: "
                        "they take the readings as gravity (the paper's Assumption 1, a sheet held still), so a "
                        "moving sheet's own acceleration becomes shape error")
    p.add_argument("--prior", choices=PRIOR_CHOICES, default=DEFAULT_PRIOR,
                   help=f"global method: what fills in what the readings cannot determine "
                        f"(default {DEFAULT_PRIOR}: the lattice's bending held only where the "
                        "sheet is level; adaptive: held everywhere, the default before, biased "
                        "where lattice lines turn in plan, as on a draped sheet; off: the "
                        "readings alone, a level sheet undefined; fixed, local: older priors "
                        "towards square cells). docs/estimator.md section 3 compares them")
    p.add_argument("--jobs", type=T.int_range(1, 256), default=min(2, os.cpu_count() or 1),
                   help="worker processes of the accelerometer-only methods (default: min(2, cores)); "
                        "the fused method runs in this process and starts none")
    p.add_argument("--batch", type=T.int_range(1, 1_000_000), default=256, help="snapshots per batch (default 256)")
    p.add_argument("--uncertainty", action="store_true",
                   help="also compute yaw_std / joint_std for every snapshot (sampled: tens of times slower); "
                        "with --subscribe, joint_std about once a second per sheet")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (alone on stdout)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    from host.cli.subscribe import add_subscribe_args, check_subscribe
    add_subscribe_args(p)
    p.add_check(check_subscribe)
    p.set_defaults(func=run)


#: ``--prior`` choices and default: `host.analysis.estimator.PRIORS` and ``DEFAULT_PRIOR``, written
#: out here so that building the parser imports no estimator (a test holds them equal)
PRIOR_CHOICES = ("level", "adaptive", "off", "fixed", "local")
DEFAULT_PRIOR = "level"

#: ``--method`` choices; ``auto`` resolves to `FUSED` or ``global`` by what the recording carries
METHODS = ("auto", "global", "paper", "fused")
FUSED = "fused"


def batched() -> bool:
    """Whether ``method="global"`` goes through `host.analysis.estimator.estimate_batch` (numpy,
    `GROUP` snapshots per pass) or `estimate` one snapshot at a time, each warm-started from the one
    before: one at a time when the estimator's compiled kernel is built (`USE_KERNEL`; measured
    0.95 against 1.31 ms of CPU per 14x14 snapshot), batched otherwise (numpy alone: 1.0 against
    1.5 ms)."""
    from host.analysis.estimator import kernel  # the switch where the estimator reads it
    return not kernel.USE_KERNEL


#: Snapshots `host.analysis.estimator.estimate_batch` solves together (measured best at 14x14:
#: 16 gave 1.0 ms per snapshot against 1.7 ms one at a time, 64 gave 1.8 ms: larger groups
#: start further from their snapshots and their arrays leave the cache).
GROUP = 16


def estimate_batch(readings: np.ndarray, valid: np.ndarray, rows: int, cols: int, L: float,
                   method: str = "global", uncertainty: bool = False,
                   prior: str | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Estimate a batch, warm-starting each snapshot from the previous one (``method="global"``: one
    at a time, or `GROUP` at a time by `host.analysis.estimator.estimate_batch`: `batched`). A dead
    or stuck chip's link is masked out of its snapshot, as the live host does.

    Parameters
    ----------
    readings : ndarray, shape (n, n_links, 3), m/s²
    valid : ndarray of bool, shape (n, n_links)
    prior : str, optional
        The global method's prior (`host.analysis.estimator.PRIORS`; None: its default).
    uncertainty : bool
        Also evaluate every estimate's ``yaw_std`` / ``joint_std`` (computed on first access, and
        the dominant cost when asked for).

    Returns
    -------
    joints : ndarray, shape (n, rows, cols, 3), float64, metres (NaN for a snapshot with no valid link)
    residual : ndarray, shape (n,)
    extra : dict
        ``yaw_std`` / ``joint_std`` stacked, when asked for and the estimator provides them; ``cpu_s`` the
        process CPU time the batch took (what a shared machine does not inflate as much as wall time);
        ``skipped`` {reason: count} of the snapshots with valid links the estimator refused (their
        joints NaN, as a snapshot with no valid link), e.g. every valid link's reading implausible.
    """
    from host.analysis.estimator import estimate, estimate_batch as solve_batch
    from host.analysis.estimator.priors import DEFAULT_PRIOR

    prior = DEFAULT_PRIOR if prior is None else prior
    pkw = {"prior": prior} if method == "global" else {}
    cpu0 = time.process_time()
    n = readings.shape[0]
    joints = np.full((n, rows, cols, 3), np.nan)
    residual = np.full(n, np.nan)
    extra: dict[str, list] = {}
    has = np.asarray(valid, dtype=bool).any(axis=1)
    skipped: dict[str, int] = {}  # why a snapshot with valid links has no estimate -> how many

    def one_by_one():  # each warm-started from the one before (the global method)
        prev = None
        for k in np.flatnonzero(has):
            try:
                est = estimate(np.asarray(readings[k], dtype=float), rows, cols, L,
                               valid=np.asarray(valid[k], dtype=bool), method=method,
                               previous=prev if method == "global" else None, bad_readings="mask",
                               **pkw)
            except ValueError as exc:  # e.g. every valid link implausible: this snapshot only
                skipped[str(exc)] = skipped.get(str(exc), 0) + 1
                continue
            prev = est
            yield k, est

    pairs = None
    if method == "global" and batched():  # many snapshots per numpy pass, each warm-started
        idx = np.flatnonzero(has)
        try:
            ests = solve_batch(np.asarray(readings[idx], dtype=float), rows, cols, L,
                               valid=np.asarray(valid[idx], dtype=bool), batch=GROUP,
                               bad_readings="mask", prior=prior)
            pairs = zip(idx, ests)
        except ValueError:  # a snapshot the estimator refuses: this batch one at a time, to name it
            pairs = None
    if pairs is None:
        pairs = one_by_one()
    for k, est in pairs:
        joints[k] = est.joints
        residual[k] = est.residual
        for name in ("yaw_std", "joint_std") if uncertainty else ():
            val = getattr(est, name, None)
            if val is not None:
                extra.setdefault(name, [None] * n)[k] = np.asarray(val)
    out_extra: dict = {}
    for name, vals in extra.items():  # a snapshot with nothing to estimate: NaN, as its joints
        like = next(v for v in vals if v is not None)
        out_extra[name] = np.stack([np.full(like.shape, np.nan) if v is None else v for v in vals])
    out_extra["cpu_s"] = time.process_time() - cpu0
    out_extra["skipped"] = skipped
    return joints, residual, out_extra


#: why `estimate_fused_batch` left a snapshot with valid links unestimated
NO_GYRO = "no gyroscope record in the snapshot (the fused method needs one per link it shapes)"
RESTARTED = "its sample time went back (a SYNC counter restarted): the fused estimator started again"
STALE = "no link's record newer than the snapshot before's (a conversion repeated for two SYNCs close together)"


def estimate_fused_batch(b, fused, units: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Consecutive snapshots into the fused estimator, in order (`host.cli.demo.fused_update`, as
    ``capsheet demo`` feeds it live: each link at its own sample time, links without a gyroscope
    record masked). Returns what `estimate_batch` returns; ``residual`` is eq. (8) of the fused
    directions and normals over the units whose four links the snapshot had.

    Parameters
    ----------
    b : host.record.SnapshotBatch
        With ``gyro`` (and ``mag``, ``sample_time_s`` when recorded).
    fused : host.analysis.motion.MotionEstimator
        Carries its state into the next batch.
    units : ndarray of int, shape (n_units, 4)
        The lattice's units (`protocol.lattice.Lattice.units`).
    """
    from types import SimpleNamespace

    from host.analysis.estimator.joints import eq8_residual
    from host.analysis.motion.snapshots import fused_update

    cpu0 = time.process_time()
    n = len(b)
    rows, cols = fused.rows, fused.cols
    joints = np.full((n, rows, cols, 3), np.nan)
    residual = np.full(n, np.nan)
    skipped: dict[str, int] = {}
    # what the figure shows of the estimator itself, per snapshot (NaN where it did not run)
    info = {"gyro_bias_rms_dps": np.full(n, np.nan), "common_accel_mps2": np.full(n, np.nan),
            "mag_weight_mean": np.full(n, np.nan), "heading_absolute": np.zeros(n, dtype=bool)}
    for k in range(n):
        valid = np.asarray(b.valid[k], dtype=bool)
        if not valid.any():
            continue  # counted by the caller (no valid link)
        gyro = None if b.gyro is None else np.asarray(b.gyro[k], dtype=float)
        if gyro is None or not (valid & np.isfinite(gyro[:, 0])).any():
            skipped[NO_GYRO] = skipped.get(NO_GYRO, 0) + 1
            continue
        n_links = valid.shape[0]
        snap = SimpleNamespace(
            timestamp=float(b.timestamp[k]), valid=valid, readings=np.asarray(b.readings[k], dtype=float), gyro=gyro,
            mag=None if b.mag is None else np.asarray(b.mag[k], dtype=float),
            sample_time_s=(np.full(n_links, np.nan) if b.sample_time_s is None
                           else np.asarray(b.sample_time_s[k], dtype=float)))
        out = fused_update(fused, snap)
        if out is None:
            why = RESTARTED if fused.sample_times_s is None else STALE
            skipped[why] = skipped.get(why, 0) + 1
            continue
        joints[k] = out.joints
        whole = units[out.valid[units].all(axis=1)]
        frames = out.motion.frames
        residual[k] = eq8_residual(whole, frames[:, :, 0], frames[:, :, 2]) if whole.size else 0.0
        m, v = out.motion, out.valid
        info["gyro_bias_rms_dps"][k] = np.degrees(np.sqrt(np.mean(np.sum(m.gyro_bias_rps[v] ** 2, axis=1))))
        info["common_accel_mps2"][k] = np.linalg.norm(m.common_accel_mps2)
        if m.mag_weight is not None:
            info["mag_weight_mean"][k] = float(np.mean(m.mag_weight[v]))
        info["heading_absolute"][k] = bool(m.heading_absolute)
    return joints, residual, {"cpu_s": time.process_time() - cpu0, "skipped": skipped, "fused_info": info}


def _import_estimator() -> None:
    import host.analysis.estimator  # noqa: F401 -- imported for the work that follows


def _source(args):
    """``(lattice, L, session, batches, total, truncated)``: the recording's snapshots as an iterator
    of `host.record.recording.SnapshotBatch` of ``--batch`` each, read as they are consumed (``total``: the
    snapshot count if known beforehand, else None; ``truncated``: the MCAP was cut short, its
    summary missing)."""
    from host.record.recording import SnapshotBatch, iter_snapshots, snapshot_count
    from host.record.replay import Replay
    from protocol.lattice import Lattice

    src, path = args.source, Path(args.recording)
    if path.suffix.lower() == ".mcap" and not args.from_raw:
        it = iter_snapshots(src, args.batch)
        first = next(it, None)
        if first is None:
            raise ValueError(f"{str(path)!r} holds no snapshot (try --from-raw)")
        session = first.session
        lat = Lattice(int(session["rows"]), int(session["cols"]))
        L = float(args.link_length or session.get("link_length_m", 0.01))
        total = snapshot_count(src)  # None: no summary, the file was cut short
        return lat, L, session, _chain(first, it), total, total is None
    rp = Replay(src, lattice=args.lattice, link_length=args.link_length)
    snaps = list(rp.snapshots())
    if not snaps:
        raise ValueError(f"{str(path)!r}: the replay made no snapshot")
    session = rp.recording.session if rp.recording else {}
    n_links = rp.lattice.n_links
    imu = {}  # the IMU axes of 6/9-axis chips, NaN where a snapshot had none (as host.record reads them)
    for name, shape in (("gyro", (n_links, 3)), ("mag", (n_links, 3)), ("sample_time_s", (n_links,))):
        have = [getattr(s, name, None) for s in snaps]
        if any(v is not None for v in have):
            imu[name] = np.stack([np.full(shape, np.nan) if v is None else v for v in have]).astype(np.float32)
    whole = SnapshotBatch(session, np.array([s.counter for s in snaps], dtype=np.uint16),
                          np.array([s.timestamp for s in snaps]), np.array([s.wall_time for s in snaps]),
                          np.stack([s.readings for s in snaps]).astype(np.float32), np.stack([s.valid for s in snaps]),
                          np.stack([s.status for s in snaps]), **imu)
    parts = (SnapshotBatch(session, *(getattr(whole, f)[k:k + args.batch] for f in _FIELDS),
                           **{name: v[k:k + args.batch] for name, v in imu.items()})
             for k in range(0, len(whole), args.batch))
    return rp.lattice, rp.link_length, session, parts, len(whole), bool(rp.recording and rp.recording.truncated)


#: `host.record.recording.SnapshotBatch`'s array fields, in order
_FIELDS = ("counter", "timestamp", "wall_time", "readings", "valid", "status")


def resolve_method(method: str, gyro, recording) -> str:
    """``--method`` for this recording: ``auto`` is `FUSED` when its first snapshots carry
    gyroscopes (``gyro``: their array, or None), else ``global``. ValueError for `FUSED` on a
    recording without them (the one line says what to run instead)."""
    has_gyro = gyro is not None and bool(np.isfinite(gyro).any())
    if method == "auto":
        return FUSED if has_gyro else "global"
    if method == FUSED and not has_gyro:
        raise ValueError(f"--method fused needs gyroscopes, and {str(recording)!r} carries accelerometers only "
                         "(record 6/9-axis chips with capsheet host --sensors accel+gyro); use --method global")
    return method


def _chain(first, rest):
    yield first
    yield from rest


def run(args) -> int:
    if args.subscribe is not None:
        from host.cli.subscribe import run_worker
        return run_worker(args)
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    from host.cli.progress import Progress

    t_start = time.monotonic()
    # one file, a split set by its name, or its files in order (host.record.read)
    args.source = args.recording[0] if len(args.recording) == 1 else [str(p) for p in args.recording]
    args.recording = args.recording[0] if len(args.recording) == 1 else " + ".join(map(str, args.recording))

    def start_pool():
        """The worker processes, each importing the estimator (scipy: ~0.5 s) at once."""
        import multiprocessing as mp
        started = ProcessPoolExecutor(max_workers=args.jobs, mp_context=mp.get_context("fork"))
        for _ in range(args.jobs):
            started.submit(_import_estimator)
        return started

    # Only the accelerometer-only methods use the workers (the fused one runs in this process, in
    # order). Named on the command line, the workers start now and import while this process reads
    # the file; with ``auto`` once the first batch says which method it is.
    pool = start_pool() if args.jobs > 1 and args.method not in ("auto", FUSED) else None
    try:
        try:
            lat, L, session, batches, total, truncated = _source(args)
        except (ValueError, OSError) as exc:
            print(f"capsheet estimate: {exc}", file=sys.stderr)
            return 1
        from host.cli.replay import truncated_note
        if truncated and truncated_note("capsheet estimate", args.recording, args.allow_truncated, "estimates it"):
            return 1
        rows, cols = lat.rows, lat.cols
        first = next(batches)
        batches = _chain(first, batches)
        try:
            method = resolve_method(args.method, first.gyro, args.recording)
            if method == FUSED and args.uncertainty:
                raise ValueError("--uncertainty is for the accelerometer-only methods (global, paper); the fused "
                                 "method has none")
        except ValueError as exc:  # a method the recording cannot take: the option is wrong for it
            print(f"capsheet estimate: {exc}", file=sys.stderr)
            return 2
        fused = None
        if method == FUSED:  # one state from snapshot to snapshot: in this process, in order
            from host.analysis.motion import MotionEstimator
            fused = MotionEstimator(rows, cols, L)
            units = np.asarray(lat.units).reshape(-1, 4)
        elif pool is None and args.jobs > 1:
            pool = start_pool()
        t_est = time.monotonic()
        parts: list = []  # [SnapshotBatch, joints, residual, extra] in file order
        cpu_s = 0.0
        skipped: dict[str, int] = {}
        fused_info: dict[int, dict] = {}  # batch index -> the fused estimator's own figures (for the PNG)
        bar = Progress(total, "estimate", "snapshot", quiet=args.quiet)

        def done(k, result):
            nonlocal cpu_s
            j, r, ex = result
            cpu_s += ex.pop("cpu_s")
            for why, count in ex.pop("skipped").items():
                skipped[why] = skipped.get(why, 0) + count
            if "fused_info" in ex:
                fused_info[k] = ex.pop("fused_info")
            parts[k][1:] = [j, r, ex]
            bar.update(j.shape[0])

        try:
            # Batches are estimated as they are read: with --jobs, the workers estimate the first
            # ones while this process reads (and decodes) the rest; at most 2 per worker wait.
            pending: dict = {}
            for b in batches:
                parts.append([b, None, None, None])
                k = len(parts) - 1
                if fused is not None:
                    done(k, estimate_fused_batch(b, fused, units))
                    continue
                if pool is None:
                    done(k, estimate_batch(b.readings, b.valid, rows, cols, L, method,
                                           args.uncertainty, args.prior))
                    continue
                pending[pool.submit(estimate_batch, b.readings, b.valid, rows, cols, L, method,
                                    args.uncertainty, args.prior)] = k
                while len(pending) > 2 * args.jobs:
                    finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for f in finished:
                        done(pending.pop(f), f.result())
            while pending:
                finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                for f in finished:
                    done(pending.pop(f), f.result())
        except KeyboardInterrupt:
            bar.close()
            print("capsheet estimate: interrupted; nothing written", file=sys.stderr)
            return 130
        except (ValueError, OSError) as exc:  # a record further in the file that cannot be used
            bar.close()
            print(f"capsheet estimate: {exc}; nothing written", file=sys.stderr)
            return 1
        bar.close()
    finally:
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
    t_done = time.monotonic()
    cat = {f: np.concatenate([getattr(p[0], f) for p in parts]) for f in _FIELDS}
    counter, ts, wall, readings, valid, status = (cat[f] for f in _FIELDS)
    joints = np.concatenate([p[1] for p in parts])
    residual = np.concatenate([p[2] for p in parts])
    n = counter.shape[0]
    if n and not np.isfinite(residual).any():  # a recording that could not be used: no output, exit 1
        no_link = int(n - np.count_nonzero(valid.any(axis=1)))
        why = ", ".join([f"{no_link} with no valid link"] * bool(no_link)
                        + [f"{c}: {w}" for w, c in sorted(skipped.items())])
        print(f"capsheet estimate: none of the {n} snapshots of {args.recording} could be estimated ({why}); "
              f"nothing written", file=sys.stderr)
        return 1
    extra_arrays = {}
    for name in set().union(*(p[3] for p in parts)):
        if all(name in p[3] for p in parts):
            extra_arrays[name] = np.concatenate([p[3][name] for p in parts])
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".npz":
        # uncompressed: float joints do not compress (13 % smaller, 13x the time: a third of a second
        # per 10 s of 14x14 at 145 Hz, a third of the whole offline budget)
        np.savez(out, counter=counter, timestamp=ts, joints=joints, residual=residual, valid=valid,
                 link_length_m=L, lattice=np.array([rows, cols]), **extra_arrays)
    else:
        _write_mcap(out, lat, L, session, counter, ts, wall, readings, valid, status, joints, residual,
                    extra_arrays, quiet=args.quiet, method=method,
                    imu={name: np.concatenate([getattr(p[0], name) for p in parts])
                         for name in ("gyro", "mag", "sample_time_s")
                         if all(getattr(p[0], name) is not None for p in parts)})
    jobs = 1 if fused is not None else min(args.jobs, len(parts))
    t_written = time.monotonic()
    result = {"recording": str(args.recording), "out": str(out), "lattice": f"{rows}x{cols}", "link_length_m": L,
              "truncated": truncated,
              "snapshots": n, "estimated": int(np.count_nonzero(np.isfinite(residual))), "jobs": jobs,
              "batch": args.batch, "method": method, "uncertainty": bool(args.uncertainty),
              "sensors": ("accel+gyro+mag" if first.mag is not None else "accel+gyro" if first.gyro is not None
                          else "accel"),
              "recorded_duration_s": round(float(ts[-1] - ts[0]), 3) if n > 1 else 0.0,
              "first_batch_s": round(t_est - t_start, 3), "estimate_s": round(t_done - t_est, 3),
              "write_s": round(t_written - t_done, 3), "total_s": round(time.monotonic() - t_start, 3),
              "snapshots_per_s": round(n / max(t_done - t_est, 1e-9), 1),
              "not_estimated": {"no_valid_link": int(n - np.count_nonzero(valid.any(axis=1))),
                                "refused": sum(skipped.values()), "reasons": skipped},
              "estimator_cpu_s": round(cpu_s, 3),
              "snapshots_per_cpu_s": round(n / max(cpu_s, 1e-9), 1)}
    if n > 1 and ts[-1] > ts[0]:
        # the whole job (reading, estimating, writing) against the recorded time
        result["faster_than_real_time"] = round(float(ts[-1] - ts[0]) / max(time.monotonic() - t_start, 1e-9), 2)
    if args.png is not None:
        from host.cli.figures import estimate_run_figure
        png = Path(args.png) if args.png else out.with_suffix(".png")
        gyro = (np.concatenate([p[0].gyro for p in parts]) if all(p[0].gyro is not None for p in parts)
                else None)
        info = ({name: np.concatenate([fused_info[k][name] for k in range(len(parts))]) for name in fused_info[0]}
                if fused is not None and len(fused_info) == len(parts) else None)
        estimate_run_figure(png, ts - ts[0], residual, valid, joints, lat, L, gyro=gyro, fused=info,
                            title=f"capsheet estimate: {Path(args.recording).name}, {rows}x{cols}, "
                                  f"L = {100 * L:g} cm, {n} snapshots, method {method}"
                                  + (f" ({result['sensors']})" if gyro is not None else ""))
        result["png"] = str(png)
        print(f"capsheet estimate: wrote {png}", file=sys.stderr)
    for why, count in sorted(skipped.items()):
        print(f"capsheet estimate: {count} snapshot(s) not estimated: {why}", file=sys.stderr)
    print(f"capsheet estimate: {result['estimated']} of {n} snapshots estimated ({method}"
          f"{', ' + result['sensors'] if method == FUSED else ''}) in {result['estimate_s']} s "
          f"({result['snapshots_per_s']}/s, {jobs} job{'s' if jobs > 1 else ''}) -> {out}", file=sys.stderr)
    if args.json:
        print(json.dumps(result, indent=1))
    return 0


def _write_mcap(out, lat, L, session, counter, ts, wall, readings, valid, status, joints, residual, extra,
                quiet: bool, method: str = "global", imu: dict | None = None) -> None:
    from types import SimpleNamespace

    from host.snapshots.snapshot import LatticeSnapshot
    from host.cli.progress import Progress
    from host.record.recording import Recorder

    rec = Recorder(out, lat, L, session={"mode": "estimate", "estimated_from": session.get("format", "?"),
                                         **{k: v for k, v in session.items() if k in ("rate_hz", "sync", "mode")}})
    try:
        bar = Progress(counter.shape[0], "write", "snapshot", quiet=quiet)
        for k in range(counter.shape[0]):
            bar.update()
            snap = LatticeSnapshot(int(counter[k]), float(ts[k]), float(wall[k]), readings[k], valid[k], status[k],
                                   bool(valid[k].all()), 0.0, **{name: v[k] for name, v in (imu or {}).items()})
            rec.snapshot(snap)
            if np.isfinite(residual[k]):
                est = SimpleNamespace(joints=joints[k], valid=valid[k], residual=float(residual[k]), method=method,
                                      iterations=0, **{name: v[k] for name, v in extra.items()})
                rec.estimate(est, int(counter[k]), float(ts[k]), float(wall[k]))
        bar.close()
    finally:
        rec.close()
