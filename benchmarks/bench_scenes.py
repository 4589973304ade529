"""The moving scenes and the 6/9-axis chips: what each scene asks of the sensors, and how
fast the simulator makes ground truth and readings. Prints JSON.

For every scene of `virtual_sheet.motion.MOTION_SCENES` (defaults) on 14x14 and 32x32 joints,
L = 1 cm, 145 Hz:

* ``peak_accel_mps2``, ``peak_rate_dps``: the largest link acceleration and angular rate over
  ``--seconds`` (the fused estimator needs at least 2 m/s² in every moving scene);
* ``truth_s_per_s``: seconds of one core to make one simulated second of truth
  (`MotionScene.sample`, 1 s chunks), and ``read9_s_per_s`` the same with the 9-axis chips'
  readings (`virtual_sheet.imu.simulate`, ICM-42688-P + LIS3MDL); ``minutes_for_10_min``: the
  latter times 600 s, in minutes (ten minutes at 145 Hz in reasonable time).

``--png DIR`` also draws ``DIR/motion_scenes.png`` (each moving scene at three instants, and its
peaks over time) and ``DIR/imu_stream.png`` (one elbow link's gyroscope, accelerometer and
magnetometer readings against the truth).

    .venv/bin/python benchmarks/bench_scenes.py [--seconds 6] [--lattices 14 32] [--png out]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"  # one core, before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from protocol.lattice import Lattice  # noqa: E402
from virtual_sheet.imu import imu_array, simulate  # noqa: E402
from virtual_sheet.magfield import EarthField, MagneticField  # noqa: E402
from virtual_sheet.motion import MOTION_SCENES, make_motion_scene, sample_times  # noqa: E402

L = 0.01
RATE = 145.0
FIELD = MagneticField(EarthField(50e-6, np.radians(60.0), 0.0))
#: the instants the figure shows per scene: at rest, and two telling moments
SNAPSHOTS = {"carry": (0.0, 1.5, 3.5), "wave": (0.0, 2.0, 2.25), "elbow": (0.0, 0.5, 1.25),
             "tap": (0.1, 0.28, 0.5), "flat_turn": (0.0, 2.5, 5.0)}


def measure(name: str, n: int, seconds: float) -> dict:
    scene = make_motion_scene(name, n, n, L)
    t = sample_times(seconds, RATE)
    per = int(RATE)
    c0 = time.process_time()
    peak_a = peak_w = 0.0
    for k in range(0, t.size, per):
        tr = scene.sample(t[k:k + per])
        peak_a = max(peak_a, float(np.linalg.norm(tr.acceleration, axis=-1).max()))
        peak_w = max(peak_w, float(np.linalg.norm(tr.angular_velocity, axis=-1).max()))
    c1 = time.process_time()
    imu = imu_array(Lattice(n, n).n_links, "accel+gyro+mag", seed=1, field=FIELD, rate_hz=RATE)
    for _tr, _r in simulate(scene, imu, seconds):
        pass
    c2 = time.process_time()
    return {"scene": name, "lattice": f"{n}x{n}", "moving": MOTION_SCENES[name].moving,
            "peak_accel_mps2": round(peak_a, 3), "peak_rate_dps": round(float(np.degrees(peak_w)), 1),
            "truth_s_per_s": round((c1 - c0) / seconds, 4), "read9_s_per_s": round((c2 - c1) / seconds, 4),
            "minutes_for_10_min": round((c2 - c1) / seconds * 600 / 60, 2)}


def figures(out: Path, seconds: float) -> list[str]:
    from host.cli.figures import imu_stream_figure, motion_scenes_figure

    panels = []
    t = np.arange(0.0, seconds, 1 / RATE)
    for name in [k for k, s in MOTION_SCENES.items() if s.moving]:
        scene = make_motion_scene(name, 14, 14, L)
        tr = scene.sample(t)
        a = np.linalg.norm(tr.acceleration, axis=-1).max(axis=1)
        w = np.degrees(np.linalg.norm(tr.angular_velocity, axis=-1).max(axis=1))
        picks = [int(round(x * RATE)) for x in SNAPSHOTS[name] if x < seconds]
        panels.append({"name": name, "t_s": t, "peak_accel_mps2": a, "peak_rate_dps": w,
                       "snapshots": [(float(t[i]), tr.joints[i]) for i in picks]})
    paths = [str(out / "motion_scenes.png")]
    motion_scenes_figure(paths[0], panels, lattice="14x14", link_length=L, rate_hz=RATE)
    scene = make_motion_scene("elbow", 14, 14, L)
    imu = imu_array(364, "accel+gyro+mag", seed=1, field=FIELD, rate_hz=RATE)
    (tr, r), = list(simulate(scene, imu, 3.0, chunk_s=3.0))
    k = 12 * 14 + 7  # the forearm end of the middle column (an i-link)
    B = np.einsum("tji,tj->ti", tr.frames[:, k], FIELD.at(tr.position[:, k]))
    paths.append(str(out / "imu_stream.png"))
    imu_stream_figure(paths[1], tr.t_s, [
        ("gyroscope", "°/s", np.degrees(tr.angular_velocity[:, k]), np.degrees(r.gyro_rps[:, k])),
        ("accelerometer", "m/s²", tr.specific_force[:, k], r.accel_mps2[:, k]),
        ("magnetometer", "µT", B * 1e6, r.mag_t[:, k] * 1e6)],
        title=f"elbow scene, link {k} (forearm end): ICM-42688-P + LIS3MDL chip, uncalibrated, 145 Hz\n"
              "(the readings' offsets are the chip's bias, cross-axis terms, hard iron and mounting)")
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="simulated seconds per scene (default 6)")
    ap.add_argument("--lattices", type=int, nargs="+", default=[14, 32], help="joints per side (default 14 32)")
    ap.add_argument("--png", type=Path, default=None, help="also draw the figures into this folder")
    args = ap.parse_args(argv)
    if not args.seconds > 0 or any(n < 2 for n in args.lattices):
        ap.error("--seconds must be > 0 and every lattice >= 2")
    rows = [measure(name, n, args.seconds) for n in args.lattices for name in MOTION_SCENES]
    out = {"benchmark": "scenes", "rate_hz": RATE, "seconds": args.seconds, "link_length_m": L,
           "every_moving_scene_reaches_2_mps2": all(r["peak_accel_mps2"] >= 2.0 for r in rows if r["moving"]),
           "rows": rows}
    if args.png is not None:
        out["figures"] = figures(args.png, args.seconds)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
