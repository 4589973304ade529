"""The fused estimator's magnetometer steps (`host.analysis.motion.fused.MotionEstimator`, step 4
of its docstring; docs/estimator.md §8 "Magnetometers" and "Disturbances"): every link's heading
and its weight, the per-link disturbance tests, and the sheet's heading held against a
disturbance by the robust mode of its links' residuals. A mixin: the state is the estimator's."""

from __future__ import annotations

import numpy as np

from ._linalg import mag_terms, robust_mode, rotation_matrices, turn_all, wrap


class MagnetometerSteps:
    """`MotionEstimator`'s magnetometer methods (the state they use is set up by its
    ``_initialise``: ``_b_ref``, ``_dist``, ``_dist_count``, ``_resid_avg``, ``_weights``,
    ``_mode_psi``)."""

    def _magnetometer(self, m, v):
        """Per link: the weight (information, 1/rad²) of its magnetometer's heading and its
        heading's offset from Earth's field (rad) (module docstring, step 4).

        The weight is the magnetometer's noise and floor, with two tests of a local disturbance
        averaged over `FusedConfig.disturbance_tau_s` (`_disturbance_tests`): the field's
        magnitude and dip against Earth's measure two of the three components of what a
        disturbance adds to the field, and the third, the one that turns the heading, is taken
        to be as large (its variance added to the heading's); the heading against the loops'
        solution scales the weight by ``1 / (1 + (s / scale)²)``. ``self._weights`` keeps each
        link's weight as a fraction of an undisturbed one's, in [0, 1]."""
        cfg = self.config
        F, dip = self._b_ref
        e, hz, t_field, t_dip = mag_terms(self.R, m, self.declination_rad, F, dip,
                                          cfg.disturbance_field_frac, cfg.disturbance_dip_rad)
        ok = v & (hz > 0.1 * F)
        self._field_tests = (ok, t_field, t_dip)
        hz2 = np.maximum(hz, 1e-30) ** 2
        var0 = cfg.mag_noise_t ** 2 / hz2 + cfg.mag_floor_rad ** 2
        # what the averaged field tests show beyond their noise (3x its mean: the 95 % point of
        # the 2-degree-of-freedom chi-square), tesla², a bias over `disturbance_persist_s`
        # their noise: the magnetometer's, averaged, and the link's tilt (the dip is measured in
        # the world frame the link's estimated orientation gives)
        a = self._dist_alpha(self._dt_last)
        noise2 = 2.0 * cfg.mag_noise_t ** 2 * a / (2.0 - a) \
            + F * F * (self.P[:, 0, 0] + self.P[:, 1, 1])
        dist2 = ((self._dist[:, 1] * cfg.disturbance_field_frac) ** 2
                 + (self._dist[:, 2] * cfg.disturbance_dip_rad) ** 2) * F * F
        lasts = cfg.disturbance_persist_s / max(self._h, 1e-6)
        dist2 = np.maximum(dist2 - 3.0 * noise2, 0.0) * lasts
        s2 = self._dist[:, 0] ** 2
        wgt = var0 / (var0 + dist2 / hz2) / (1.0 + s2 / cfg.disturbance_scale ** 2)
        # until the tests have averaged over their time constant a link's magnetometer is not
        # used: a magnet there from the start would otherwise be believed first
        warm = self._dist_count * self._h >= cfg.mag_warmup_s
        self._weights = np.where(ok & warm, wgt, 0.0)
        mw = np.where(ok, self._weights / np.where(ok, var0, 1.0), 0.0)
        e = np.where(ok, e, 0.0)
        return mw, e

    def _heading_mode(self, dt) -> None:
        """Turn the sheet's heading towards the robust mode of its links' averaged heading
        residuals (`robust_mode`), by the part of the heading the magnetometers' weights do not
        hold (``held0``, `_yaw_prior`) over `FusedConfig.heading_mode_time_s`: the gyroscopes
        carry the heading while a disturbance is detected, and the links that agree with each
        other — not the mean of every link the disturbance turns a little — correct it slowly.
        The links vote in proportion to how much their groups are held: a group whose
        magnetometers are trusted has taken their heading in the solve, its residuals are zero
        by construction (docs/estimator.md §8)."""
        cfg = self.config
        if cfg.heading_mode_rad <= 0 or self._held0 <= 0:
            return
        use = self._field_tests[0] & (self._dist_count * self._h >= cfg.mag_warmup_s)
        w = np.where(use, self._held[self.topo.group], 0.0)
        psi = robust_mode(self._resid_avg, w, cfg.heading_mode_rad, self._mode_psi)
        if psi is None:
            return
        g = self._held0 * min(1.0, self._h / cfg.heading_mode_time_s)
        turn_all(rotation_matrices(np.array([0.0, 0.0, -g * psi])), self.R)
        self._resid_avg -= g * psi
        self._mode_psi = (1.0 - g) * psi  # where the mode is after the turn: the next start

    def _disturbance_tests(self, resid, v, dt) -> None:
        """Average each link's tests over `FusedConfig.disturbance_tau_s`: its heading against the
        lattice's solution (``resid``, rad: what is left of its magnetometer's heading once the
        loops and every other link have had their say), its field's magnitude and dip against
        Earth's (`_magnetometer` weighs them)."""
        cfg = self.config
        ok, t_mag, t_dip = self._field_tests
        # the heading against its group's (links the loops turn alike on a flat sheet): what a
        # group shares is the shape's to explain, what one link alone shows is its own
        topo = self.topo
        g, r = topo.group, topo.n_groups
        resid = wrap(resid)
        wk = np.where(ok, 1.0 / (1.0 + self._dist[:, 1] ** 2 + self._dist[:, 2] ** 2), 0.0)
        mean = np.bincount(g, weights=wk * resid, minlength=r) / np.maximum(
            np.bincount(g, weights=wk, minlength=r), 1e-30)
        tests = np.stack([(resid - mean[g]) / cfg.disturbance_heading_rad, t_mag, t_dip], axis=1)
        self._dist_count += ok
        alpha = self._dist_alpha(dt)[:, None]
        self._dist = np.where(ok[:, None], self._dist + alpha * (tests - self._dist), self._dist)
        self._resid_avg = np.where(ok, self._resid_avg + alpha[:, 0] * (resid - self._resid_avg),
                                   self._resid_avg)

    def _dist_alpha(self, dt):
        """The tests' averaging weight per link: a running mean over the first samples, then an
        exponential one over `FusedConfig.disturbance_tau_s`."""
        return np.clip(np.maximum(dt / self.config.disturbance_tau_s,
                                  1.0 / np.maximum(self._dist_count, 1.0)), 1e-6, 1.0)
