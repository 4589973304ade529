/* The joints' Laplacian in the estimator's kernel: its supernodal L D Lᵀ solve in double, the
 * closed pitches' height fit (host/analysis/estimator/pipeline.py, closed_pitches) and the prior's
 * pair weights (host/analysis/estimator/priors.py); declared in yaw_eval.h. All arrays are
 * C-contiguous, caller-owned; nothing is allocated. No -ffast-math: the numbers are the numpy
 * code's to rounding.
 */
#include "yaw_eval.h"

#include <math.h>
#include <stddef.h>

/* ldl_solve_d_nc is compiled into each caller with its count of columns known (a loop over one
 * column at run time cost a quarter of a solve of the 64x64 sheet's Laplacian) */
#if defined(__GNUC__)
#define INLINE_ALWAYS inline __attribute__((always_inline))
#else
#define INLINE_ALWAYS inline
#endif

/* capsheet_ldl_solve's sweeps with double values (see yaw_eval.h) on nc columns at once, stored
 * interleaved (x[j * nc + c]): the factor is read once for all of them. Per supernode: forward,
 * the unit lower diagonal block (column axpys), then the rows below; backward, the rows below
 * (dot products), then the diagonal block. A one-column supernode (most of a grid Laplacian's)
 * updates x in place, without the gather. */
static INLINE_ALWAYS void ldl_solve_d_nc(int64_t n, int64_t nc, int64_t n_super, const int32_t *sn_col,
                           const int64_t *sn_row, const int32_t *rows, const int64_t *sn_diag,
                           const int64_t *sn_below, const double *val, const double *diag,
                           double *x, double *work)
{
    int64_t s, j, c;
    for (s = 0; s < n_super; ++s) {
        const int64_t c0 = sn_col[s], w = sn_col[s + 1] - c0;
        const int64_t nb = sn_row[s + 1] - sn_row[s];
        const int32_t *restrict r = rows + sn_row[s];
        const double *restrict dg = val + sn_diag[s];
        const double *restrict bl = val + sn_below[s];
        double *restrict xs = x + c0 * nc;
        double *restrict t = work;
        int64_t k, i;
        for (k = 0; k + 1 < w; ++k)
            for (i = k + 1; i < w; ++i)
                for (c = 0; c < nc; ++c)
                    xs[i * nc + c] -= dg[k * w + i] * xs[k * nc + c];
        if (nb == 0)
            continue;
        if (w == 1) {
            for (i = 0; i < nb; ++i)
                for (c = 0; c < nc; ++c)
                    x[r[i] * nc + c] -= bl[i] * xs[c];
            continue;
        }
        for (i = 0; i < nb * nc; ++i)
            t[i] = 0.0;
        for (k = 0; k < w; ++k) {
            const double *restrict b = bl + k * nb;
            for (i = 0; i < nb; ++i)
                for (c = 0; c < nc; ++c)
                    t[i * nc + c] += b[i] * xs[k * nc + c];
        }
        for (i = 0; i < nb; ++i)
            for (c = 0; c < nc; ++c)
                x[r[i] * nc + c] -= t[i * nc + c];
    }
    for (j = 0; j < n; ++j)
        for (c = 0; c < nc; ++c)
            x[j * nc + c] /= diag[j];
    for (s = n_super - 1; s >= 0; --s) {
        const int64_t c0 = sn_col[s], w = sn_col[s + 1] - c0;
        const int64_t nb = sn_row[s + 1] - sn_row[s];
        const int32_t *restrict r = rows + sn_row[s];
        const double *restrict dg = val + sn_diag[s];
        const double *restrict bl = val + sn_below[s];
        double *restrict xs = x + c0 * nc;
        double *restrict g = work;
        int64_t k, i;
        if (nb > 0 && w == 1) {
            for (c = 0; c < nc; ++c) {
                double a = 0.0;
                for (i = 0; i < nb; ++i)
                    a += bl[i] * x[r[i] * nc + c];
                xs[c] -= a;
            }
        } else if (nb > 0) {
            for (i = 0; i < nb; ++i)
                for (c = 0; c < nc; ++c)
                    g[c * nb + i] = x[r[i] * nc + c];
            for (k = 0; k < w; ++k) {
                const double *restrict b = bl + k * nb;
                for (c = 0; c < nc; ++c) {
                    const double *restrict gc = g + c * nb;
                    double a = 0.0;
                    for (i = 0; i < nb; ++i)
                        a += b[i] * gc[i];
                    xs[k * nc + c] -= a;
                }
            }
        }
        for (k = w - 2; k >= 0; --k)
            for (c = 0; c < nc; ++c) {
                double a = 0.0;
                for (i = k + 1; i < w; ++i)
                    a += dg[k * w + i] * xs[i * nc + c];
                xs[k * nc + c] -= a;
            }
    }
}

void capsheet_ldl_solve_d(int64_t n, int64_t n_super, const int32_t *sn_col, const int64_t *sn_row,
                          const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                          const double *val, const double *diag, double *x, double *work)
{
    ldl_solve_d_nc(n, 1, n_super, sn_col, sn_row, rows, sn_diag, sn_below, val, diag, x, work);
}

void capsheet_ldl_fill_d(int64_t n_super, const int32_t *l_ptr, const int32_t *l_idx,
                         const double *l_val, const int32_t *sn_col, const int64_t *sn_row,
                         const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                         int32_t *map, double *val)
{
    int64_t s, q, j;
    int32_t p;
    for (s = 0; s < n_super; ++s) {
        const int64_t c0 = sn_col[s], c1 = sn_col[s + 1], w = c1 - c0;
        const int64_t nb = sn_row[s + 1] - sn_row[s];
        const int32_t *r = rows + sn_row[s];
        for (q = 0; q < nb; ++q)
            map[r[q]] = (int32_t)q;
        for (j = c0; j < c1; ++j) {
            const int64_t k = j - c0;
            for (p = l_ptr[j]; p < l_ptr[j + 1]; ++p) {
                const int64_t i = l_idx[p];
                if (i <= j)
                    continue;
                if (i < c1)
                    val[sn_diag[s] + k * w + (i - c0)] = l_val[p];
                else if (map[i] >= 0)
                    val[sn_below[s] + k * nb + map[i]] = l_val[p];
            }
        }
        for (q = 0; q < nb; ++q)
            map[r[q]] = -1;
    }
}

void capsheet_lap_solve(const capsheet_lap_t *lap, int64_t ncols, double *b, double *work)
{
    const int64_t n = lap->n;
    double *t = work, *ldl_work = work + n * ncols;
    int64_t c, j;
    for (j = 0; j < n; ++j)
        for (c = 0; c < ncols; ++c)
            t[lap->pos[j] * ncols + c] = b[j * ncols + c];
    if (ncols == 1)  /* one column (the heights' solves): the loops over columns compiled away */
        ldl_solve_d_nc(n, 1, lap->n_super, lap->sn_col, lap->sn_row, lap->rows, lap->sn_diag,
                       lap->sn_below, lap->val, lap->diag, t, ldl_work);
    else if (ncols == 3)  /* the joints' three coordinates */
        ldl_solve_d_nc(n, 3, lap->n_super, lap->sn_col, lap->sn_row, lap->rows, lap->sn_diag,
                       lap->sn_below, lap->val, lap->diag, t, ldl_work);
    else
        ldl_solve_d_nc(n, ncols, lap->n_super, lap->sn_col, lap->sn_row, lap->rows,
                       lap->sn_diag, lap->sn_below, lap->val, lap->diag, t, ldl_work);
    for (j = 0; j < n; ++j)
        for (c = 0; c < ncols; ++c)
            b[j * ncols + c] = t[lap->pos[j] * ncols + c];
}

/* Bᵀ (w · (dz − B x)) − eps x into out (B the valid links' incidence: row k is −1 at ep_a[k],
 * +1 at ep_b[k]); dz NULL: 0; w NULL: 1. */
static void lap_weighted_residual(int64_t nj, int64_t nl, const int64_t *ep_a, const int64_t *ep_b,
                                  const double *w, const double *dz, const double *x, double eps,
                                  double sign_dz, double *out)
{
    int64_t j, k;
    for (j = 0; j < nj; ++j)
        out[j] = 0.0;
    for (k = 0; k < nl; ++k) {
        const int64_t a = ep_a[k], b = ep_b[k];
        double v = (dz ? sign_dz * dz[k] : 0.0) - (x[b] - x[a]);
        if (w)
            v *= w[k];
        out[a] -= v;
        out[b] += v;
    }
    for (j = 0; j < nj; ++j)
        out[j] -= eps * x[j];
}

void capsheet_closed_pitches(const capsheet_lap_t *lap, int64_t n_links, int64_t n_valid,
                             const int64_t *valid_links, const int64_t *ep_a, const int64_t *ep_b,
                             const double *trig_in, const double *beta, int32_t weighted,
                             double var_floor, double eps, int64_t steps, double *beta_out,
                             double *trig, double *work)
{
    const int64_t nj = lap->n;
    double *x = work, *r = x + nj, *p = r + nj, *zr = p + nj, *ap = zr + nj;
    double *dz = ap + nj, *w = dz + n_valid, *lap_work = w + n_valid;
    double rz = 0.0;
    int64_t j, k, it;
    for (k = 0; k < n_valid; ++k) {
        const double sb = trig_in[4 * valid_links[k] + 3];
        dz[k] = -sb;
        w[k] = 1.0 / (1.0 - sb * sb + var_floor);
    }
    /* the unweighted fit: x = L⁻¹ Bᵀ dz */
    for (j = 0; j < nj; ++j)
        x[j] = 0.0;
    for (k = 0; k < n_valid; ++k) {
        x[ep_a[k]] -= dz[k];
        x[ep_b[k]] += dz[k];
    }
    capsheet_lap_solve(lap, 1, x, lap_work);
    if (weighted) {
        lap_weighted_residual(nj, n_valid, ep_a, ep_b, w, dz, x, eps, 1.0, r);
        for (it = 0; it < steps; ++it) {
            double rz_new = 0.0, pap = 0.0, a;
            for (j = 0; j < nj; ++j)
                zr[j] = r[j];
            capsheet_lap_solve(lap, 1, zr, lap_work);
            for (j = 0; j < nj; ++j)
                rz_new += r[j] * zr[j];
            if (it == 0) {
                for (j = 0; j < nj; ++j)
                    p[j] = zr[j];
            } else {
                const double bq = rz_new / (rz > 0.0 ? rz : 1.0);
                for (j = 0; j < nj; ++j)
                    p[j] = zr[j] + bq * p[j];
            }
            rz = rz_new;
            /* ap = Bᵀ (w B p) + eps p = −(the residual of dz = 0 at x = p) */
            lap_weighted_residual(nj, n_valid, ep_a, ep_b, w, NULL, p, eps, 0.0, ap);
            for (j = 0; j < nj; ++j) {
                ap[j] = -ap[j];
                pap += p[j] * ap[j];
            }
            a = rz / (pap > 0.0 ? pap : 1.0);
            for (j = 0; j < nj; ++j) {
                x[j] += a * p[j];
                r[j] -= a * ap[j];
            }
        }
    }
    for (k = 0; k < n_links; ++k)
        beta_out[k] = beta[k];
    for (k = 0; k < 4 * n_links; ++k)
        trig[k] = trig_in[k];
    for (k = 0; k < n_valid; ++k) {
        const int64_t l = valid_links[k];
        double s = -(x[ep_b[k]] - x[ep_a[k]]);
        s = s < -1.0 ? -1.0 : (s > 1.0 ? 1.0 : s);
        beta_out[l] = asin(s);
        trig[4 * l + 2] = sqrt((1.0 - s) * (1.0 + s));  /* cos of a pitch in [-pi/2, pi/2] */
        trig[4 * l + 3] = s;
    }
}

void capsheet_pair_weights(int64_t n_units, const int64_t *units, const double *hu, int64_t n_links,
                           const double *link_units, int32_t level, int64_t n_bend,
                           const int64_t *pairs, const double *bridging, double bend, double share,
                           int64_t n_shear, const int64_t *shear_unit, double shear_weight,
                           double floor_w, double *w, double *lf)
{
    int64_t k, u;
    if (level) {
        for (k = 0; k < n_links; ++k)
            lf[k] = 0.0;
        for (k = 0; k < 4; ++k)  /* numpy's order: position by position */
            for (u = 0; u < n_units; ++u)
                lf[units[4 * u + k]] += hu[u];
        for (k = 0; k < n_links; ++k)
            lf[k] /= link_units[k];
    }
    for (k = 0; k < n_bend; ++k) {
        double b = bend;
        if (level) {
            const double la = lf[pairs[2 * k]], lb = lf[pairs[2 * k + 1]];
            double h = la > lb || la != la ? la : lb;  /* np.maximum (NaN propagates) */
            h = h > bridging[k] || h != h ? h : bridging[k];
            h = h > share || h != h ? h : share;
            b = bend * h;
        }
        w[k] = b > floor_w || b != b ? b : floor_w;
    }
    for (k = 0; k < n_shear; ++k) {
        const double v = shear_weight * hu[shear_unit[k]];
        w[n_bend + k] = v > floor_w || v != v ? v : floor_w;
    }
}
