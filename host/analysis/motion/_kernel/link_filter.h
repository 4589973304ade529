/* The fused estimator's per-link filter steps (host/analysis/motion/fused.py): the gyroscope's
 * propagation, the accelerometer's Kalman update, and applying a correction, for n links at
 * once. Plain C99, no allocation; arrays are row-major doubles: R n x 3 x 3 (sensor -> world),
 * P n x 6 x 6 (error state: world rotation, then gyroscope bias), vectors n x 3 or n x 6.
 * The numpy code beside it (fused.py, `_np_*`) computes the same numbers in the same order of
 * operations; tests/host/analysis/test_motion_kernel.py compares them. */
#include <stddef.h>
#include <stdint.h>

/* R <- R exp([dth]x) with dth = (w0 + w1)/2 dt + (w0 x w1) dt^2/12; P <- F P F^T + Q with
 * F = [[I, -R dt], [0, I]] (R the propagated frame), Q = diag(q I, qb I). */
void capsheet_mf_propagate(size_t n, double *R, double *P, const double *w0, const double *w1,
                           const double *dt, const double *q, const double *qb);

/* Accelerometer update: residual y = f - R^T vec, H = R^T [vec]x (3 x 6 with zero bias part),
 * S = H P H^T + r2 I, inflated by max(1, y^T S^-1 y / gate); K = P H^T S^-1; x = K y (n x 6,
 * zero where valid[k] == 0); P <- P - K H P; nis[k] = y^T S^-1 y before the inflation (the
 * normalised innovation squared, 3 degrees of freedom; NaN where valid[k] == 0). */
void capsheet_mf_accel(size_t n, const double *R, double *P, const double *f, const double *vec,
                       const double *r2, double gate, const uint8_t *valid, double *x,
                       double *nis);

/* The yaw step's update: with c = P[:, 2] (the covariance with the world-z rotation) and
 * p = c[2], x = c mu / p and P <- P - c c^T (1 - 1/(a p)) / p. */
void capsheet_mf_yaw(size_t n, double *P, const double *mu, const double *a_diag, double *x);

/* R <- exp([x[0:3]]x) R, bias <- bias + x[3:6], P <- (P + P^T) / 2. */
void capsheet_mf_apply(size_t n, double *R, double *bias, double *P, const double *x);
