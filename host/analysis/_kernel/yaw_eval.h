/* The yaw problem's cost and gradient for one snapshot (model "cells"); see yaw_eval.c. */
#ifndef CAPSHEET_YAW_EVAL_H
#define CAPSHEET_YAW_EVAL_H

#include <stdint.h>

/* One snapshot's problem: the structure's index arrays and the snapshot's coefficients. */
typedef struct {
    int64_t n_links;          /* links (the length of gamma) */
    int64_t n_units;          /* U: active units */
    int64_t n_roll;           /* K: links with a roll residual */
    int64_t n_pairs;          /* prior pairs */
    int64_t n_var;            /* nv: variables; index nv is the dummy (gauge, padding) */
    const int64_t *units;     /* (U, 4) link of every unit position */
    const int64_t *unit_var;  /* (U, 4) its variable, nv for the gauge */
    const double *c_loop;     /* (U, 4) ±cos β of eq. (4) */
    const double *Az, *Cz;    /* (U,) z of the cell's i- and j-link sums */
    const int64_t *roll_links, *roll_c0, *roll_c1, *roll_var0;  /* (K,) */
    const double *roll_ws1;   /* (K,) 1 if the link has a second cell, else 0 */
    const double *y_c;        /* (K,) complex: sensor y, xy, before the yaw */
    const double *y_z, *w;    /* (K,) sensor y's z; the roll weight */
    const int64_t *pairs, *pair_var;  /* (P, 2) links; their variables */
    const double *pair_t, *lam_b;     /* (P,) target difference; weight */
    const int64_t *var_links; /* (nv,) */
    const double *target, *lam;       /* (nv,) */
    int32_t abs_prior;        /* nonzero: apply the yaw prior λ wrap(γ − τ)² */
} capsheet_yaw_t;

/* Cost (½ Σ of the squared terms) at the yaws gamma (n_links,); grad (nv + 1,) receives the
 * gradient over the variables (entry nv: the dummy's, discarded); work holds 19 U + 2 n_links
 * doubles.
 * No failure cases: the indices are the caller's (validated when the structure is built). */
double capsheet_yaw_eval(const capsheet_yaw_t *p, const double *gamma, double *grad,
                         double *work);

/* capsheet_yaw_eval with the links' (cos γ, sin γ) given: cs (2 n_links), capsheet_link_cs's of
 * gamma (or a chord step's turning of them). No failure cases. */
double capsheet_yaw_eval_cs(const capsheet_yaw_t *p, const double *gamma, const double *cs,
                            double *grad, double *work);

/* cs (2 n) = (cos γ, sin γ) per link. No failure cases. */
void capsheet_link_cs(int64_t n, const double *gamma, double *cs);


/* Per link (n links) of readings r (n, 3) and their roll alpha = atan2(r_y, r_z) and pitch
 * beta = atan2(−r_x, hypot(r_y, r_z)) (estimator.roll_pitch): trig (n, 4) = (cos α, sin α,
 * cos β, sin β) from the reading's own ratios, without a trigonometric call except on the x
 * axis. No failure cases (NaN in, NaN out). */
void capsheet_reading_trig(int64_t n, const double *r, const double *alpha, const double *beta,
                           double *trig);

/* trig (n, 4) = (cos α, sin α, cos β, sin β) of given angles (n,) each. No failure cases. */
void capsheet_angle_trig(int64_t n, const double *alpha, const double *beta, double *trig);

/* Per link (n links), the direction d (sensor x) and normal nrm (sensor z) in world coordinates,
 * (n, 3) each, of R = Rz(γ) Ry(β) Rx(α) (docs/design.md); trig as capsheet_reading_trig's.
 * No failure cases. */
void capsheet_directions(int64_t n, const double *trig, const double *gamma, double *d,
                         double *nrm);

/* capsheet_directions with the yaws' (cos γ, sin γ) given (cs, 2 n: capsheet_link_cs's). */
void capsheet_directions_cs(int64_t n, const double *trig, const double *cs, double *d,
                            double *nrm);

/* Σ over the units (n_units, 4 links) of eq. (8): |d0 + d1 − d2 − d3|² + |n0 − n1 + n2 − n3|². */
double capsheet_eq8(int64_t n_units, const int64_t *units, const double *d, const double *nrm);

/* Per unit, λ3/λ1 of eq. (7) in the closed form of estimator.angles.solvability_units, from the
 * links' trig (capsheet_reading_trig's); NaN where a cosine of one of its 4 links is not finite
 * (a missing link). */
void capsheet_solvability(int64_t n_units, const int64_t *units, const double *trig,
                          double *ratio);

/* Per unit (all units of a rows_u x cols_u grid, row-major; links ``units`` (n, 4)), the
 * flatness h = exp(−(θ/θ0)²) of estimator.priors.flatness for one snapshot: readings r (n_links, 3),
 * their |s| in g, the (2 radius + 1)² regional mean of θ²; th2, tmp are work (rows_u cols_u each).
 * No failure cases (θ0 > 0 is the caller's). */
void capsheet_flatness(int64_t rows_u, int64_t cols_u, const int64_t *units, const double *r,
                       const double *norm_g, double g0, int64_t radius, double th0, double *th2,
                       double *tmp, double *h);

/* One snapshot's yaw-free coefficients of the yaw problem (model "cells"; estimator.yawproblem.YawProblem):
 * per unit c_loop (n_units, 4) = ±cos β, Az, Cz (n_units,) the z of its i- and j-link sums; per
 * roll link y_c (n_roll,) complex = sin β sin α + i cos α, y_z = cos β sin α; trig as
 * capsheet_reading_trig's. No failure cases. */
void capsheet_yaw_coeffs(int64_t n_units, const int64_t *units, int64_t n_roll,
                         const int64_t *roll_links, const double *trig, double *c_loop,
                         double *Az, double *Cz, double *y_c, double *y_z);


/* Solve L D Lᵀ x = b in place (x holds b on entry): a symmetric positive definite matrix's
 * factors, L unit lower triangular in supernodes. Supernode s covers the columns
 * sn_col[s] .. sn_col[s+1]-1 (w of them), which share their rows below the supernode,
 * rows[sn_row[s] .. sn_row[s+1]-1] (nb of them, any order). val[sn_diag[s] + k*w + i] holds
 * L(c0+i, c0+k) for i > k (the diagonal block, column-major; other entries unused) and
 * val[sn_below[s] + k*nb + q] holds L(rows[sn_row[s]+q], c0+k), in float: the solve streams
 * through L twice and is bound by memory; sums are kept in double. diag: D (n,). work: at least
 * the largest nb doubles. No failure cases: a zero in D gives inf/NaN. */
void capsheet_ldl_solve(int64_t n, int64_t n_super, const int32_t *sn_col, const int64_t *sn_row,
                        const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                        const float *val, const double *diag, double *x, double *work);


/* Fill the supernodal values (val, zeroed by the caller; layout as capsheet_ldl_solve's) from a
 * unit lower triangular CSC matrix (column pointers, row indices in any order, values; entries
 * on or above the diagonal are skipped) whose pattern the supernodes were built from. map: n
 * int32 set to -1 on entry, left so. An entry outside its supernode's rows is dropped (never the
 * case for the pattern they were built from). */
void capsheet_ldl_fill(int64_t n_super, const int32_t *l_ptr, const int32_t *l_idx,
                       const double *l_val, const int32_t *sn_col, const int64_t *sn_row,
                       const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                       int32_t *map, float *val);


/* The chord iterations of estimator.solver.solve_global on a kept factorisation (supernodal, float32: see
 * capsheet_ldl_solve) for one snapshot, without damping. perm_inv: position -> variable,
 * perm_of_var: variable -> position of the factorisation's ordering. gamma (n_links) and
 * cost / grad (nv + 1) hold the current point on entry and on return; iterations and prev_smax
 * (the last step's largest entry, inf at first) are carried in and out. Returns 0 converged
 * (gamma is the last step's point, unevaluated), 1 the cost rose (gamma unchanged: refactorise
 * there), 2 a step contracted by less than refactor_ratio (accepted: refactorise at gamma) while
 * below refactor_far * tol or more than refactor_growth times the last, or refactor_patience
 * such steps in a row,
 * 3 max_iter reached. work: 6 nv + n_links + 1 + ldl_work_size + 19 max(n_units, 1) + 6 n_links
 * doubles. chain_rho, chain_kappa, chain_safety: the contraction the previous snapshot measured on
 * this factorisation (estimator.solver.Contraction); when chain_safety > 0 the first step also
 * converges when chain_safety * max(rho s, kappa s^2) < tol (s its largest entry).
 * predict_within: estimator.solver.PREDICT_WITHIN (the stopping rule, step_converged). steps[0],
 * steps[1]: the first two steps' largest entries (0 where not taken). */
typedef struct {
    int64_t n_links; int64_t max_iter; double tol, refactor_ratio, anderson_cos;
    double chain_rho, chain_kappa, chain_safety, predict_within;
    int64_t refactor_patience; double refactor_far, refactor_growth;
    const double *cs_in;  /* (cos γ, sin γ) of gamma on entry (2 n_links) */
    double *cs_out;       /* ... of gamma on return (2 n_links; may not alias cs_in) */
    const int64_t *perm_inv, *perm_of_var;
    int64_t n_super; const int32_t *sn_col; const int64_t *sn_row; const int32_t *rows;
    const int64_t *sn_diag, *sn_below; const float *val; const double *diag;
    int64_t ldl_work_size;
} capsheet_chord_t;
int32_t capsheet_chord(const capsheet_yaw_t *p, double *gamma, double *cost, double *grad,
                       const capsheet_chord_t *c, int64_t *iterations, double *prev_smax,
                       double *steps, double *work);


/* capsheet_ldl_solve with the factor's values in double (the joints' Laplacian: its solves are
 * the heights and the joints themselves, not a chord step's approximation, and they must be
 * SuperLU's to rounding). Same layout; val double. No failure cases: a zero in D gives inf/NaN. */
void capsheet_ldl_solve_d(int64_t n, int64_t n_super, const int32_t *sn_col, const int64_t *sn_row,
                          const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                          const double *val, const double *diag, double *x, double *work);

/* Factorise the SPD matrix A (n x n, CSC with both triangles or the lower one: entries above the
 * diagonal are skipped) as L D Lᵀ on supernodes known to hold L's pattern (capsheet_ldl_solve's
 * layout, built from an earlier factorisation of a matrix of the same pattern): lval (n_val
 * doubles, L's values in that layout, the unit diagonal as 0), diag (n, D) and val32 (n_val, lval
 * in float, capsheet_ldl_solve's). iwork: 2 n + 3 n_super int32; work: the largest count of rows
 * below a supernode doubles. Returns 0, 1 when a pivot is not positive (not SPD: the caller
 * factorises otherwise), 2 when an entry falls outside the pattern (other supernodes). */
int32_t capsheet_ldl_factor(int64_t n, const int32_t *a_ptr, const int32_t *a_idx,
                            const double *a_val, int64_t n_super, const int32_t *sn_col,
                            const int64_t *sn_row, const int32_t *rows, const int64_t *sn_diag,
                            const int64_t *sn_below, double *lval, double *diag, float *val32,
                            int64_t n_val, int32_t *iwork, double *work);

/* capsheet_ldl_fill into double values (capsheet_ldl_solve_d's). */
void capsheet_ldl_fill_d(int64_t n_super, const int32_t *l_ptr, const int32_t *l_idx,
                         const double *l_val, const int32_t *sn_col, const int64_t *sn_row,
                         const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                         int32_t *map, double *val);

/* The joints' Laplacian factorised (estimator.structure.Structure.lap_kernel): n joints, the
 * symmetric ordering pos[joint] (position of a joint in the factor), and its supernodal L D Lᵀ
 * in double (capsheet_ldl_solve_d's layout). */
typedef struct {
    int64_t n; const int64_t *pos;
    int64_t n_super; const int32_t *sn_col; const int64_t *sn_row; const int32_t *rows;
    const int64_t *sn_diag, *sn_below; const double *val; const double *diag;
    int64_t ldl_work_size;
} capsheet_lap_t;

/* Solve the Laplacian system for ncols right-hand sides b (n, ncols) row-major (a joint's
 * columns together, numpy's (n, 3)), in place, the factor read once for all of them. work:
 * ncols (n + ldl_work_size) doubles. No failure cases. */
void capsheet_lap_solve(const capsheet_lap_t *lap, int64_t ncols, double *b, double *work);

/* estimator.pipeline.closed_pitches for one snapshot: the heights that fit every valid link's
 * step dz = -sin beta (trig_in's, the readings' capsheet_reading_trig) best, min sum w (z_b - z_a - dz)^2 + eps |z|^2 (w = 1 / (1 - sin^2 beta +
 * floor) when weighted, else 1): the unweighted fit, then `steps` conjugate-gradient steps
 * preconditioned by the unweighted Laplacian (pipeline.weighted_heights); then each valid link's
 * pitch asin(s), s = clip(-(z_b - z_a)), into beta_out (the others keep beta's) and trig
 * (n_links, 4): trig_in's with each valid link's pitch columns (sqrt(1 - s^2), s). Links: n_valid of them, valid_links, endpoints
 * ep_a, ep_b (joints). work: 7 n_joints + 2 n_valid + ldl_work_size doubles. No failure cases. */
void capsheet_closed_pitches(const capsheet_lap_t *lap, int64_t n_links, int64_t n_valid,
                             const int64_t *valid_links, const int64_t *ep_a, const int64_t *ep_b,
                             const double *trig_in, const double *beta, int32_t weighted,
                             double var_floor, double eps, int64_t steps, double *beta_out,
                             double *trig, double *work);

/* The pair weights of the "level" (level nonzero) or "adaptive" prior for one snapshot
 * (estimator.priors.prior_weights): per bending pair (pairs (n_bend, 2) links) bend times, for
 * "level", the largest of its two links' mean unit flatness (lf: per link, the mean of hu over
 * its units; link_units their counts), bridging[k] and share; per shear pair shear_weight times
 * its unit's flatness (shear_unit); each at least floor_w, into w (n_bend + n_shear). hu: every
 * unit's flatness (n_units, all units; units (n_units, 4) their links). lf: n_links doubles of
 * work. The same arithmetic as numpy's, NaN propagated as np.maximum does. No failure cases. */
void capsheet_pair_weights(int64_t n_units, const int64_t *units, const double *hu, int64_t n_links,
                           const double *link_units, int32_t level, int64_t n_bend,
                           const int64_t *pairs, const double *bridging, double bend, double share,
                           int64_t n_shear, const int64_t *shear_unit, double shear_weight,
                           double floor_w, double *w, double *lf);

#endif
