"""Rigid overlay and the paper's error metric, defined once for the estimator, tactile and figures.

The paper measures shape error by overlaying the estimate on the truth with the least-squares
rigid motion (rotation + translation), then taking each joint's distance, in % of the sheet's side.
`rigid_fit` is that overlay (Kabsch, optionally weighted); `overlay`, `overlay_error` and
`error_percent_of_side` are the metric built on it.

>>> import numpy as np
>>> q = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
>>> c, s = np.cos(0.3), np.sin(0.3)
>>> p = q @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [5.0, -2.0, 1.0]
>>> bool(np.allclose(rigid_fit(p, q), q))
True
"""

from __future__ import annotations

import numpy as np

__all__ = ["rigid_fit", "overlay", "overlay_error", "side_length", "error_percent_of_side"]


def rigid_fit(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """``src`` moved by the weighted least-squares rotation + translation onto ``dst`` (Kabsch).

    Parameters
    ----------
    src, dst : ndarray, shape (n, 3)
        Points, metres.
    weights : ndarray, shape (n,), optional
        Non-negative weight per point (default: all 1).

    Returns
    -------
    ndarray, shape (n, 3)
        ``R src + t`` with ``R`` a proper rotation (det +1, never a reflection) minimising
        ``Σ w ‖R p + t − q‖²``. Where the points are degenerate (collinear or coplanar, so the
        determinant's sign is 0) the rotation keeps det +1.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = (src - cs).T @ ((dst - cd) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return (src - cs) @ R.T + cd


def _check_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape != b.shape or a.shape[-1] != 3:
        raise ValueError(f"Expected `estimate_joints` and `true_joints` to have the same shape "
                         f"(..., 3), got {a.shape} and {b.shape}.")
    return a, b


def overlay(estimate_joints: np.ndarray, true_joints: np.ndarray) -> np.ndarray:
    """Estimate moved onto truth by the least-squares rigid motion (rotation + translation, Kabsch).

    Parameters
    ----------
    estimate_joints, true_joints : ndarray, shape (rows, cols, 3) (or (n, 3))
        Joints, metres.

    Returns
    -------
    ndarray, same shape
        ``R p + t`` for every estimated joint, with ``R`` a proper rotation (no reflection) and
        ``(R, t)`` minimising ``Σ ‖R p + t − q‖²``.
    """
    a, b = _check_pair(estimate_joints, true_joints)
    return rigid_fit(a.reshape(-1, 3), b.reshape(-1, 3)).reshape(a.shape)


def overlay_error(estimate_joints: np.ndarray, true_joints: np.ndarray) -> np.ndarray:
    """Per-joint distance between estimate and truth after the least-squares rigid overlay.

    Returns
    -------
    ndarray, shape (rows, cols) (the input's shape without the last axis)
        Distances, metres.
    """
    a, b = _check_pair(estimate_joints, true_joints)
    return np.linalg.norm(overlay(a, b) - b, axis=-1)


def side_length(rows: int, cols: int, link_length: float) -> float:
    """A sheet's side, the length every "% of side" in capsheet is of: its longer side as laid
    out flat, ``(max(rows, cols) − 1) · L`` metres (the paper's sheets are square: 13 L).

    >>> side_length(14, 14, 0.01), side_length(6, 11, 0.01)
    (0.13, 0.1)
    """
    if min(int(rows), int(cols)) < 2 or not (np.isfinite(link_length) and link_length > 0):
        raise ValueError(f"Invalid sheet: {rows}x{cols} joints, L = {link_length!r} (need >= 2x2, L > 0)")
    return round((max(int(rows), int(cols)) - 1) * float(link_length), 12)


def error_percent_of_side(estimate_joints: np.ndarray, true_joints: np.ndarray,
                          link_length: float) -> np.ndarray:
    """Per-joint error as the paper reports it: `overlay_error` in % of the sheet's side length.

    The side is `side_length` (the longer side; the paper's sheets are square, 13 units of
    ``L``). The paper's Fig. 10 plots the mean and standard deviation of this over all joints and
    trials.

    Returns
    -------
    ndarray, shape (rows, cols)
        Percent.
    """
    a, b = _check_pair(estimate_joints, true_joints)
    if a.ndim != 3:
        raise ValueError(f"Expected joints of shape (rows, cols, 3), got {a.shape}.")
    return 100.0 * overlay_error(a, b) / side_length(a.shape[0], a.shape[1], link_length)
