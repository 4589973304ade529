"""The fused estimator's absolute attitude over a minute: what the shape error hides.
Prints JSON.

`bench_motion.py` scores shapes after the rigid overlay, which removes a tilt of the whole sheet.
The fused estimator takes the accelerometers' common part as the sheet's translation and holds
the sheet's tilt against gravity by the translation's bounds (`FusedConfig.sheet_position_std_m`
and `FusedConfig.sheet_velocity_std_mps`): with magnetometers (Earth's field dipping 60°) a tilt
error also turns the magnetic heading. This runs the same chips and calibration as
`bench_motion.py` (9-axis, 14x14, L = 1 cm, 1 % g, 145 Hz) for longer, with each
``--position-stds`` value (1000: a sheet taken to move without bound, its tilt unheld), and prints per
scene and configuration: ``mean_error_pct_side`` (the
shape, as bench_motion), ``tilt_err_deg`` (the links' mean angle between the estimated and the true
gravity direction in the sensor frame, mean over the run and over its last second) and
``heading_err_deg`` (bench_motion's heading error, the same two spans).

    .venv/bin/python benchmarks/bench_motion_attitude.py [--seconds 60] [--scenes tap flat_turn carry] [--position-stds 0.1 1000]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

import bench_motion as bm  # noqa: E402
from host.analysis.metrics import error_percent_of_side  # noqa: E402
from host.analysis.motion import FusedConfig, MotionEstimator, calibrated  # noqa: E402
from virtual_sheet.motion import MOTION_SCENES, make_motion_scene  # noqa: E402


def run(name: str, seconds: float, stds: list[float], cal, n: int, seed: int) -> list[dict]:
    scene = make_motion_scene(name, n, n, bm.L)
    truth, rd = bm.capture(scene, bm.chips(n, seed), seconds)
    acc, gyr, mag = calibrated(cal, rd["accel_mps2"], rd["gyro_rps"], rd["mag_t"])
    t = rd["t_s"]
    last = t >= t[-1] - 1.0
    out = []
    for std in stds:
        est = MotionEstimator(n, n, bm.L, config=FusedConfig(
            sheet_position_std_m=std, sheet_velocity_std_mps=max(0.5, std)))
        err, tilt, head = (np.empty(t.size) for _ in range(3))
        for k in range(t.size):
            e = est.update(t[k], acc[k], gyr[k], mag[k])
            err[k] = error_percent_of_side(e.joints, truth["joints"][k], bm.L).mean()
            c = np.einsum("ki,ki->k", e.frames[:, 2, :], truth["frames"][k][:, 2, :])
            tilt[k] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).mean()
            head[k] = abs(np.degrees(bm.heading_error(e.frames[None], truth["frames"][k][None]))[0])
        out.append({"scene": name, "seconds": seconds, "sensors": "accel+gyro+mag",
                    "sheet_position_std_m": std,
                    "mean_error_pct_side": round(float(err.mean()), 4),
                    "tilt_err_deg": round(float(tilt.mean()), 3),
                    "tilt_err_last_s_deg": round(float(tilt[last].mean()), 3),
                    "heading_err_deg": round(float(head.mean()), 3),
                    "heading_err_last_s_deg": round(float(head[last].mean()), 3)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--scenes", nargs="*", default=["tap", "flat_turn", "carry"])
    ap.add_argument("--position-stds", type=float, nargs="*", default=[0.1, 1000.0],
                    help="the sheet's position spread the estimator is told, m (FusedConfig."
                         "sheet_position_std_m; 1000: unbounded)")
    ap.add_argument("--lattice", type=int, default=14)
    args = ap.parse_args(argv)
    bad = [s for s in args.scenes if s not in MOTION_SCENES]
    if bad or args.seconds <= 0 or not all(np.isfinite(x) and x > 0 for x in args.position_stds):
        print(f"bench_motion_attitude.py: invalid arguments (unknown scenes {bad}, seconds "
              f"{args.seconds}, position stds {args.position_stds}: each > 0)", file=sys.stderr)
        return 2
    n = args.lattice
    cal, _cpu = bm.calibrate(n)
    rows = []
    for i, name in enumerate(args.scenes):
        try:
            rows += run(name, args.seconds, args.position_stds, cal, n, 400 + i)
        except ValueError as exc:  # the simulator cannot make every scene for every duration
            rows.append({"scene": name, "seconds": args.seconds, "error": str(exc)})
    print(json.dumps({"lattice": f"{n}x{n}", "rows": rows, "load": " ".join(f"{x:.2f}" for x in os.getloadavg())}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
