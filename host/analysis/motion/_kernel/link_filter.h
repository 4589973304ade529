/* The fused estimator's per-link filter steps (host/analysis/motion/fused.py): the gyroscope's
 * propagation, the accelerometer's Kalman update, and applying a correction, for n links at
 * once. Plain C99, no allocation; arrays are row-major doubles: R n x 3 x 3 (sensor -> world),
 * P n x 6 x 6 (error state: world rotation, then gyroscope bias), vectors n x 3 or n x 6.
 * The numpy code beside it (fused.py, `_np_*`) computes the same numbers to rounding (the
 * kernel takes a small rotation's series where numpy takes sin and cos, and a symmetric
 * update's upper triangle); tests/host/analysis/test_motion_kernel.py compares them. */
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

/* The lattice step's residuals, weights and Jacobian (fused.py `_np_lattice`, the same numbers in
 * the same order): n links, n_units cells, n_pairs (link, cell) pairs, nnz Jacobian entries.
 * units n_units x 4, pair_link / pair_cell n_pairs, inv_ncell n, jac_slots (8 n_units + n +
 * 4 n_pairs: each computed entry's place in the CSR data, summed there in that order),
 * jac_indptr / jac_indices (the CSR pattern: 2 n_units + n + 1 row starts, nnz columns; all
 * index arrays 32-bit, half the memory a pass reads). Out: res and wts
 * (2 n_units + n rows: closure x, y per cell, then one normal row per link), jd (nnz), lat_diag
 * (n: the diagonal of J^T W J). work: 10 n_units + 3 n doubles of scratch. */
void capsheet_mf_lattice(size_t n, size_t n_units, size_t n_pairs, size_t nnz, const double *R,
                         const double *P, const int32_t *units, const int32_t *pair_link,
                         const int32_t *pair_cell, const double *inv_ncell,
                         const int32_t *jac_slots, const int32_t *jac_indptr,
                         const int32_t *jac_indices, double floor2, double *res, double *wts,
                         double *jd, double *lat_diag, double *work);

/* out = J^T (w .* (J x)) for the CSR matrix J (n_rows x n: indptr, indices, data); tmp holds
 * n_rows doubles. Each out entry sums its terms in increasing row order (as a CSR product
 * by J^T's rows would). */
void capsheet_mf_normal_matvec(size_t n_rows, size_t n, const int32_t *indptr,
                               const int32_t *indices, const double *data, const double *w,
                               const double *x, double *tmp, double *out);

/* The lattice step's yaw solve (fused.py `_linalg.pcg` on `MotionEstimator._yaw_prior`'s
 * matrix): conjugate gradients with the preconditioner inv_diag, from zero, on
 * A = J^T W J + prior + diag(mw), where J is the CSR matrix (n_rows x n: indptr, indices,
 * data), W = diag(w), and the prior is the nested one: with abar_g = sum_{k in g} D_k x_k / dg_g,
 * ey = sum_g Eg_g abar_g and s_g = Eg_g abar_g - Eg_g ey / sE + Eg_g ey I0 / sE^2,
 * (prior x)_k = D_k x_k - D_k abar_{g(k)} + D_k s_{g(k)} / dg_{g(k)}. Stops when
 * |r|^2 <= rtol^2 |b|^2 or after maxiter iterations. The preconditioner is inv_diag, plus,
 * when coarse_inv (n_groups x n_groups) is not NULL, the groups' coarse correction
 * Z coarse_inv Z^T (Z the groups' indicator; coarse_inv the inverse of Z^T A Z): the modes a
 * group's links share, which the diagonal does not see. work: n_rows + 4 n + 4 n_groups
 * doubles. Returns the iterations taken. */
int capsheet_mf_yaw_pcg(size_t n, size_t n_rows, size_t n_groups, const int32_t *indptr,
                        const int32_t *indices, const double *data, const double *w,
                        const double *D, const int64_t *group, const double *dg,
                        const double *Eg, double sE, double I0, const double *mw,
                        const double *b, const double *inv_diag, const double *coarse_inv,
                        double rtol, int maxiter, double *x, double *work);

/* C = (J Z)^T W (J Z), n_groups x n_groups, row-major: J Z's entries by row (indptr n_rows + 1,
 * each entry's group grp and value val), W = diag(w). The lattice's part of the yaw problem's
 * coarse matrix (fused.py `_linalg.coarse_matrix`). */
void capsheet_mf_coarse(size_t n_rows, size_t n_groups, const int64_t *indptr,
                        const int64_t *grp, const double *val, const double *w, double *C);

/* R[k] <- Q R[k] for every link (Q 3 x 3, row-major): a turn of the whole sheet. */
void capsheet_mf_rotate(size_t n, double *R, const double *Q);

/* The magnetometers' terms (fused.py `_np_mag_terms`): W = R m (the field in the world), its
 * heading less the declination wrapped to [-pi, pi), its horizontal magnitude hz, and the two
 * field tests in their units: t_field = (|W| / field - 1) / field_unit and
 * t_dip = (asin(clip(-W_z / max(|W|, 1e-30), -1, 1)) - dip) / dip_unit. */
void capsheet_mf_mag_terms(size_t n, const double *R, const double *m, double declination,
                           double field, double dip, double field_unit, double dip_unit,
                           double *heading, double *hz, double *t_field, double *t_dip);

/* Every link's orientation covariance for the output: out[k] = P[k][0:3, 0:3] plus tilt_cov
 * (2 x 2, row-major) on its tilt block and yaw_add[k] on its yaw (none when yaw_add is NULL). */
void capsheet_mf_orientation_cov(size_t n, const double *P, const double *tilt_cov,
                                 const double *yaw_add, double *out);

/* A link direction's second derivative, world (fused.py `relative_accelerations`):
 * out[k] = R[k] (w x (w x e_x) + wdot x e_x), w and wdot in the link's frame. */
void capsheet_mf_ddot(size_t n, const double *R, const double *w, const double *wdot,
                      double *out);

/* capsheet_mf_ddot with wdot from the rates w and the last two wm1, wm2 over dt (s): the
 * second-order backward difference (3 w - 4 wm1 + wm2) / (2 dt) when second_order, else
 * (w - wm1) / dt (fused.py `_relative_accel`, the same numbers). */
void capsheet_mf_ddot_rates(size_t n, const double *R, const double *w, const double *wm1,
                            const double *wm2, const double *dt, int second_order, double *out);

/* capsheet_mf_accel, then capsheet_mf_apply of its x, link by link (one pass over the state;
 * the covariance's update, symmetric, computed once per entry: the two calls' numbers to
 * rounding), then, when turn (3 x 3) is not NULL, R <- turn R, and when turn_bias (2) is not
 * NULL, bias <- bias + R^T (turn_bias[0], turn_bias[1], 0) with that R: the sheet's common
 * tilt and bias correction (fused.py `_accel_update`), in the same pass. */
void capsheet_mf_accel_apply(size_t n, double *R, double *bias, double *P, const double *f,
                             const double *vec, const double *r2, double gate,
                             const uint8_t *valid, double *x, double *nis, const double *turn,
                             const double *turn_bias);

/* capsheet_mf_yaw, then capsheet_mf_apply of its x, link by link, then R <- turn R when turn is
 * not NULL (the sheet's heading, fused.py `_heading_mode`), and, when cov is not NULL, the
 * link's capsheet_mf_orientation_cov of the updated P into cov (n x 3 x 3) in the same pass. */
void capsheet_mf_yaw_apply(size_t n, double *R, double *bias, double *P, const double *mu,
                           const double *a_diag, double *x, const double *turn,
                           const double *tilt_cov, const double *yaw_add, double *cov);

/* out = J^T v for the CSR matrix J (n_rows x n): each out entry sums its terms in increasing row
 * order (as scipy's product by J^T's CSR does). */
void capsheet_mf_jt_times(size_t n_rows, size_t n, const int32_t *indptr, const int32_t *indices,
                          const double *data, const double *v, double *out);

/* What the loops say of each group's common yaw offset (fused.py `_lattice_update`): jg, J's
 * entries jd summed per (row, group) slot jg_index; info[g] = sum over the slots of group g of
 * w[row] jg^2; seen[g] = info[g] / max(sum of lat_diag over the group's links, 1e-300). */
void capsheet_mf_group_info(size_t nnz, size_t n_jg, size_t n_groups, size_t n,
                            const int32_t *jg_index, const double *jd, const int32_t *jg_rows,
                            const int32_t *jg_group, const double *w, const int64_t *group,
                            const double *lat_diag, double *jg, double *info, double *seen);

/* The magnetometers' weights (fused.py `_linalg.np_mag_weights`, `MotionEstimator._magnetometer`),
 * per link: var0 = noise2 / hz2 + floor2 with hz2 = max(hz, 1e-30)^2; the tests' averaging
 * weight a = clip(max(dt / tau, 1 / max(count, 1)), 1e-6, 1); their noise
 * n2 = 2 noise2 a / (2 - a) + (F F) (P[0][0] + P[1][1]); what the averaged field tests show
 * beyond it, d2 = max(((dist1 field_unit)^2 + (dist2 dip_unit)^2) F F - 3 n2, 0) lasts;
 * wgt = var0 / (var0 + d2 / hz2) / (1 + dist0^2 / scale2); weight = wgt where ok and
 * count h >= warmup, else 0; mw = weight / var0 where ok, else 0; e = 0 where not ok. */
void capsheet_mf_mag_weights(size_t n, const double *hz, const uint8_t *ok, const double *dist,
                             const double *P, const double *count, const double *dt,
                             double noise2, double floor2, double F, double field_unit,
                             double dip_unit, double tau, double lasts, double scale2, double h,
                             double warmup, double *weight, double *mw, double *e);

/* The disturbance tests' averages (fused.py `_linalg.np_dist_tests`,
 * `MotionEstimator._disturbance_tests`), for the links where ok: resid wrapped to [-pi, pi);
 * each group's mean of it weighted 1 / (1 + dist1^2 + dist2^2) over its ok links (sums in link
 * order; sums: 2 n_groups of work); count += 1; a = clip(max(dt / tau, 1 / max(count, 1)),
 * 1e-6, 1); dist += a ((resid - mean) / heading_unit, t_mag, t_dip) - a dist; resid_avg +=
 * a (resid - resid_avg). Links not ok keep everything. */
void capsheet_mf_dist_tests(size_t n, size_t n_groups, const int64_t *group, const uint8_t *ok,
                            const double *resid, const double *t_mag, const double *t_dip,
                            const double *dt, double tau, double heading_unit, double *dist,
                            double *resid_avg, double *count, double *sums);

/* Tukey's biweight mode from start (fused.py `_linalg.robust_mode` with a start): iterations
 * reweighted means of r, each weighted w (1 - ((r - psi) / width)^2)^2 within width of psi, links
 * with w <= 0 left out. Returns NaN when nothing has weight. */
double capsheet_mf_robust_mode(size_t n, const double *r, const double *w, double width,
                               double start, int iterations);


/* The gyroscopes' fixed errors as a consider state (_consider.py, whose numpy functions give
 * the same numbers): m blocks (1 or 2) of nine entries each, a fixed 3 x 3 matrix per chip that
 * multiplies an input u_b (the rate; the specific force's change in g), so the rate error is
 * sum_b E_b u_b. C (n, 6, nc = 9 m) each link's error's cross-covariance with the entries
 * (row-major, block by block), s2 (nc) their variances, U (n, m, 3) the inputs.
 * _propagate follows capsheet_mf_propagate (R the new frames): with G = R dt and
 * Gamma = -G [Omega(u_1) ... Omega(u_m)], P += F C Gamma^T + Gamma C^T F^T + Gamma diag(s2)
 * Gamma^T and C <- F C + Gamma diag(s2). _accel precedes capsheet_mf_accel (P its prior):
 * C <- C - K H C_theta with that update's gain, gate included. _yaw precedes capsheet_mf_yaw:
 * C <- C - c (1 - 1 / (a_diag p)) / p C_yaw, c the covariance's yaw column, p its yaw entry. */
void capsheet_mf_consider_propagate(size_t n, size_t m, const double *R, double *P, double *C,
                                    const double *U, const double *dt, const double *s2);
void capsheet_mf_consider_accel(size_t n, size_t nc, const double *R, const double *P,
                                double *C, const double *f, const double *vec, const double *r2,
                                double gate, const uint8_t *valid);
void capsheet_mf_consider_yaw(size_t n, size_t nc, const double *P, double *C,
                              const double *a_diag);
