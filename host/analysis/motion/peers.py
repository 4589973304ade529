"""The peers the fused estimator is measured against, run on the same data.

* `accel_only`: today's estimator (`host.analysis.estimator.estimate`, ``method="global"``, warm
  started snapshot to snapshot) on the accelerometers alone: the paper's Assumption 1 (no motion
  acceleration) is violated as soon as the sheet moves.
* `per_link_filter`: an orientation filter on every link on its own — VQF (Laidig & Seel,
  Information Fusion 2023: the best published per-node filter; the ``vqf`` package, optional:
  ``pip install 'capture-sheet[motion]'``) — followed by today's joints-from-directions step
  (`host.analysis.estimator.joints_from_directions`). Without magnetometers a per-link filter has
  no heading at all; each link's is aligned once, at the first snapshot, to the
  accelerometer-only estimate of that snapshot (the sheet still), and carried by its gyroscope
  from there. With magnetometers each link's heading is its own magnetometer's.

Both take whole runs (arrays over time): they are measured, not run live.
"""

from __future__ import annotations

import numpy as np

from ..estimator import estimate, joints_from_directions
from .fused import frames_from_angles

#: snapshots turned into joints at once by `per_link_filter`
_CHUNK = 4096

__all__ = ["accel_only", "per_link_filter", "frames_from_quaternions", "yaw_of_frames",
           "have_vqf"]


def _run(name: str, a, T: int | None, n: int) -> np.ndarray:
    x = np.asarray(a, dtype=float)
    if x.ndim != 3 or x.shape[1:] != (n, 3) or (T is not None and x.shape[0] != T):
        want = f"({T if T is not None else 'T'}, {n}, 3)"
        raise ValueError(f"Expected `{name}` to have shape {want}, got {x.shape}.")
    return x


def accel_only(accel_mps2, rows: int, cols: int, link_length: float) -> list:
    """Today's estimator on every snapshot, each warm-started from the one before.

    Parameters
    ----------
    accel_mps2 : ndarray, shape (T, n_links, 3)
        Calibrated specific force, m/s², link frames.

    Returns
    -------
    list of `host.analysis.estimator.ShapeEstimate`, one per snapshot (readings far from 1 g —
    a link accelerating hard — are masked out, ``bad_readings="mask"``).
    """
    n = 2 * rows * cols - rows - cols
    a = _run("accel_mps2", accel_mps2, None, n)
    out, prev = [], None
    for k in range(a.shape[0]):
        prev = estimate(a[k], rows, cols, link_length, previous=prev, bad_readings="mask")
        out.append(prev)
    return out


def have_vqf() -> bool:
    """True when the ``vqf`` package (the per-link peer) can be imported."""
    try:
        import vqf  # noqa: F401
    except ImportError:
        return False
    return True


def frames_from_quaternions(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions ``(..., 4)``, scalar first (w, x, y, z)."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def yaw_of_frames(R: np.ndarray) -> np.ndarray:
    """The heading of frames ``(..., 3, 3)`` (sensor -> world): the angle about world z of the
    rotation that takes each to its yaw-free form, from the horizontal part of whichever of the
    sensor's x and y axes is the more horizontal."""
    x, y = R[..., :, 0], R[..., :, 1]
    use_x = np.abs(x[..., 2]) <= np.abs(y[..., 2])
    return np.where(use_x, np.arctan2(x[..., 1], x[..., 0]),
                    np.arctan2(y[..., 1], y[..., 0]) - np.pi / 2)


def per_link_filter(t_s, accel_mps2, gyro_rps, rows: int, cols: int, link_length: float,
                    mag_t=None, *, declination_rad: float = 0.0,
                    with_frames: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """VQF on every link, then the joints from the links' directions (module docstring).

    Parameters
    ----------
    t_s : ndarray, shape (T,)
        Sample times, s, evenly spaced (VQF takes one sample period).
    accel_mps2, gyro_rps : ndarray, shape (T, n_links, 3)
        Calibrated, link frames.
    mag_t : ndarray, shape (T, n_links, 3), optional
        Calibrated, link frames: VQF's 9-axis output (heading from each magnetometer, world x
        magnetic north turned by ``declination_rad``); without: its 6-axis output, aligned once.

    Returns
    -------
    joints : ndarray, shape (T, rows, cols, 3)
    frames : ndarray, shape (T, n_links, 3, 3), or None with ``with_frames=False``
        Each link's sensor -> world rotation.

    Raises
    ------
    ImportError
        Without the ``vqf`` package (``pip install 'capture-sheet[motion]'``).
    """
    try:
        from vqf import VQF
    except ImportError as exc:
        raise ImportError(f"The per-link peer needs the vqf package (pip install "
                          f"'capture-sheet[motion]'): {exc}") from exc
    n = 2 * rows * cols - rows - cols
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or t.size < 2 or not np.all(np.diff(t) > 0):
        raise ValueError(f"Expected `t_s` of shape (T,), T >= 2, increasing; got shape {t.shape}.")
    T = t.size
    acc = _run("accel_mps2", accel_mps2, T, n)
    gyr = _run("gyro_rps", gyro_rps, T, n)
    mag = None if mag_t is None else _run("mag_t", mag_t, T, n)
    dt = float(np.median(np.diff(t)))
    key = "quat6D" if mag is None else "quat9D"
    q = np.empty((T, n, 4))
    for k in range(n):
        f = VQF(dt)
        args = [np.ascontiguousarray(gyr[:, k]), np.ascontiguousarray(acc[:, k])]
        if mag is not None:
            args.append(np.ascontiguousarray(mag[:, k]))
        q[:, k] = f.updateBatch(*args)[key]
    R0 = frames_from_quaternions(q[0])
    if mag is None:  # align each link's heading once, at the first snapshot
        ref = estimate(acc[0], rows, cols, link_length, bad_readings="mask")
        R_ref = frames_from_angles(*(np.nan_to_num(a) for a in (ref.alpha, ref.beta, ref.yaws)))
        off = yaw_of_frames(R_ref) - yaw_of_frames(R0)
    else:  # VQF's earth frame is east-north-up: north (+y) is at the declination from world x
        off = np.full(n, declination_rad - np.pi / 2)
    Z = np.zeros((n, 3, 3))
    Z[:, 0, 0], Z[:, 0, 1], Z[:, 2, 2] = np.cos(off), -np.sin(off), 1.0
    Z[:, 1, 0], Z[:, 1, 1] = np.sin(off), np.cos(off)
    joints = np.empty((T, rows, cols, 3))
    frames = np.empty((T, n, 3, 3)) if with_frames else None
    for a in range(0, T, _CHUNK):  # in chunks: a long run's frames need not all be in memory
        R = np.einsum("kij,tkjl->tkil", Z, frames_from_quaternions(q[a:a + _CHUNK]))
        joints[a:a + _CHUNK] = joints_from_directions(R[..., 0], rows, cols, link_length)
        if with_frames:
            frames[a:a + _CHUNK] = R
    return joints, frames
