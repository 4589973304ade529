"""What every link of the sheet shares: its tilt error and its translation (the fused
estimator's step 2, docs/estimator.md §8 "the common tilt").

A tilt of the whole sheet by ``c`` and a translation acceleration ``g × c`` read the same on
every chip at one instant, so the per-link accelerometer updates, which take the common
acceleration from the accelerometers themselves, measure each link's tilt *relative to the
sheet's* and nothing of the sheet's own. That is told apart over time: a sheet's velocity and
position stay bounded, so its translation averages out while a tilt persists. This module is the
small Kalman filter that does it, with the covariance that says how well it does:

state (error states for the tilt and its rate, whole state for the motion), world frame,
horizontal::

    c  (2)  the common tilt error, rad (a rotation about world x and y shared by every link)
    β  (2)  its rate, rad/s: what the links' gyroscope biases share (a calibration's residual
            is not independent from chip to chip), handed back to every link's bias
    v  (2)  the sheet's horizontal velocity, m/s
    p  (2)  the sheet's horizontal position about its mean, m

The measured common acceleration ``m`` (the links' mean specific force turned into the world,
less gravity and the lattice's relative accelerations) drives ``v̇ = m + G c`` with
``G c = (G0 c_y, −G0 c_x)`` (what a tilt ``c`` of the frames takes off the measured
acceleration), ``ṗ = v``; ``ċ = β`` plus the links' process noise averaged over the sheet, and
``β`` walks as the biases do. A
sheet is not carried away for good: ``v = 0 ± σ_v`` and ``p = 0 ± σ_p`` enter as measurements,
each taken as one independent look per its correlation time (so with variance
``σ² · τ / Δt`` per sample), and that is what makes ``c`` observable.
"""

from __future__ import annotations

import numpy as np

from ..estimator import G0


class CommonMotion:
    """The sheet's common tilt and translation filter (module docstring).

    Parameters
    ----------
    tilt_var0 : float
        Variance of the common tilt at the start, rad² (per axis).
    velocity_std_mps, velocity_time_s : float
        The sheet's velocity spread about zero and its correlation time.
    position_std_m, position_time_s : float
        The sheet's position spread about its mean and its correlation time.
    """

    def __init__(self, tilt_var0: float, rate_var0: float, velocity_std_mps: float,
                 velocity_time_s: float, position_std_m: float, position_time_s: float) -> None:
        self.x = np.zeros(8)  # c, β (both 0 after `take`), v, p
        self.C = np.zeros((8, 8))
        self.C[0, 0] = self.C[1, 1] = tilt_var0
        self.C[2, 2] = self.C[3, 3] = rate_var0
        # the motion starts still (the first snapshot initialises on a sheet at rest)
        for i in range(4, 8):
            self.C[i, i] = 1e-6
        self.sv, self.tv = velocity_std_mps, velocity_time_s
        self.sp, self.tp = position_std_m, position_time_s

    def step(self, m_xy: np.ndarray, h: float, q_tilt: float, q_rate: float,
             r_accel: float) -> None:
        """Propagate over ``h`` seconds with the measured common acceleration ``m_xy`` (m/s²,
        world x, y), the common tilt's process noise ``q_tilt`` (rad² per axis over ``h``), its
        rate's ``q_rate`` ((rad/s)² over ``h``) and the variance of ``m_xy``'s noise
        ``r_accel`` ((m/s²)² per axis); then the bounded velocity and position as
        measurements."""
        F = np.eye(8)
        F[0, 2] = F[1, 3] = -h  # ċ = −β (β: the rate the frames' error grows by; `take`)
        F[4, 1], F[5, 0] = h * G0, -h * G0  # v gains G c over h
        F[6, 4] = F[7, 5] = h  # p gains v over h
        F[6, 1], F[7, 0] = 0.5 * h * h * G0, -0.5 * h * h * G0
        x = self.x
        v_new = x[4:6] + h * m_xy
        x[6:8] += h * x[4:6] + 0.5 * h * h * m_xy
        x[4:6] = v_new
        C = F @ self.C @ F.T
        C[0, 0] += q_tilt
        C[1, 1] += q_tilt
        C[2, 2] += q_rate
        C[3, 3] += q_rate
        C[4, 4] += h * h * r_accel
        C[5, 5] += h * h * r_accel
        # the bounded motion: v = 0 and p = 0, each an independent look per correlation time
        rv = self.sv ** 2 * max(self.tv / h, 1.0)
        rp = self.sp ** 2 * max(self.tp / h, 1.0)
        for idx, r in ((4, rv), (5, rv), (6, rp), (7, rp)):
            s = C[idx, idx] + r
            k = C[:, idx] / s
            x -= k * x[idx]
            C -= np.outer(k, C[idx, :])
        self.C = 0.5 * (C + C.T)

    def take(self) -> tuple[np.ndarray, np.ndarray]:
        """The common tilt correction (rad, world x, y: every frame is turned by it) and the
        common bias correction (rad/s, world x, y: every link's bias gains it, in its own
        frame) the filter has found; both error states are reset to zero."""
        c, b = self.x[:2].copy(), self.x[2:4].copy()
        self.x[:4] = 0.0
        return c, b

    @property
    def tilt_cov(self) -> np.ndarray:
        """The common tilt's covariance, 2 x 2, rad², world x and y (the filter's; what the
        accelerometers' fixed errors add is `add_fixed_tilt`'s)."""
        return self.C[:2, :2].copy()


def add_fixed_tilt(cov: np.ndarray, common: np.ndarray, R: np.ndarray, j_links: np.ndarray,
                   config) -> tuple[np.ndarray, np.ndarray]:
    """Every link's orientation covariance ``cov`` (n, 3, 3) and the part all links share,
    ``common`` (2, 2), with what the accelerometers' fixed errors add to the tilts (the filter
    follows the accelerometers' frames, and each link's frame lies off its chip's by them,
    which nothing the sheet reads tells from a tilt); ``cov`` in place; ``R`` the links' frames,
    ``j_links`` the j-links' indices. Returns both.

    * each chip's own (`FusedConfig.accel_fixed_error_rad`, per horizontal axis): to its link;
    * the rotation the chips' frames share, ``w`` (`accel_common_fixed_error_rad`, its
      variance ``Σ`` diagonal in the board's axes): a calibration leaves it alike in the world
      while the sheet lay on its board (flat, as the lattice is drawn: an i-link along world x,
      a j-link along y, z up), fixed in the chips' frames since. A link turned by ``D = R Fᵀ``
      since (``F`` its frame on the board) carries it as ``D w``: alike on every link while the
      sheet moves as one body, each its own as the sheet bends. Split as the links' mean ``D̄ w``,
      which all share (to ``common`` and every link), and each link's ``(D − D̄) w`` (to its
      own; told as independent from link to link, though neighbours' are alike: the tilt NEES's
      mean needs only each link's variance). Told as a tilt common in the world, a wave's or
      an elbow's links had claimed their shared part alike while it is turned apart with them
      (docs/estimator.md §8)."""
    if s2 := config.accel_fixed_error_rad ** 2:
        cov[:, 0, 0] += s2
        cov[:, 1, 1] += s2
    c2 = np.broadcast_to(np.square(config.accel_common_fixed_error_rad, dtype=float), (3,))
    if c2.any():  # per axis of the board (x, y, z)
        D = R[:, :2, :].copy()  # its rows: world x, y; an i-link's F is I
        D[j_links, :, 0] = -R[j_links, :2, 1]  # a j-link's is a quarter turn about z
        D[j_links, :, 1] = R[j_links, :2, 0]
        Db = D.mean(axis=0)
        X = D - Db
        XS = X * c2
        shared = (Db * c2) @ Db.T
        xy = np.einsum("kc,kc->k", XS[:, 0], X[:, 1])
        cov[:, 0, 0] += np.einsum("kc,kc->k", XS[:, 0], X[:, 0]) + shared[0, 0]
        cov[:, 1, 1] += np.einsum("kc,kc->k", XS[:, 1], X[:, 1]) + shared[1, 1]
        cov[:, 0, 1] += xy + shared[0, 1]
        cov[:, 1, 0] += xy + shared[1, 0]
        common = common + shared
    return cov, common
