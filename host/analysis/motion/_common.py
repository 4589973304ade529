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
    fixed_tilt_var : float
        What the accelerometers' shared fixed error adds to the sheet's tilt, rad² per axis
        (`FusedConfig.accel_common_fixed_error_rad`): nothing the sheet reads tells it from a
        tilt, so it is not estimated, only reported with the tilt's covariance (`tilt_cov`).
    """

    def __init__(self, tilt_var0: float, rate_var0: float, velocity_std_mps: float,
                 velocity_time_s: float, position_std_m: float, position_time_s: float,
                 fixed_tilt_var: float = 0.0) -> None:
        self.x = np.zeros(8)  # c, β (both 0 after `take`), v, p
        self.C = np.zeros((8, 8))
        self.C[0, 0] = self.C[1, 1] = tilt_var0
        self.C[2, 2] = self.C[3, 3] = rate_var0
        # the motion starts still (the first snapshot initialises on a sheet at rest)
        for i in range(4, 8):
            self.C[i, i] = 1e-6
        self.sv, self.tv = velocity_std_mps, velocity_time_s
        self.sp, self.tp = position_std_m, position_time_s
        self.fixed_tilt_var = fixed_tilt_var

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
        """The common tilt's covariance, 2 x 2, rad², world x and y (the accelerometers'
        shared fixed error included)."""
        c = self.C[:2, :2].copy()
        if self.fixed_tilt_var:
            c[0, 0] += self.fixed_tilt_var
            c[1, 1] += self.fixed_tilt_var
        return c


def add_fixed_tilt(cov: np.ndarray, config) -> np.ndarray:
    """Every link's orientation covariance ``cov`` (n, 3, 3) with what its own accelerometer's
    fixed error adds to its tilt (`FusedConfig.accel_fixed_error_rad`), in place: the filter
    follows the accelerometers' frames and each link's frame lies off its chip's by that error,
    which nothing the sheet reads tells from a tilt. Returns ``cov``."""
    if s2 := config.accel_fixed_error_rad ** 2:
        cov[:, 0, 0] += s2
        cov[:, 1, 1] += s2
    return cov
