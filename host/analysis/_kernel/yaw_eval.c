/* The yaw problem's cost and gradient for one snapshot, model "cells" (host/analysis/estimator/yawproblem.py,
 * YawProblem.evaluate with jac=False, and _roll_grad): the same terms in one pass over the
 * units, roll links and prior pairs, for the Python fallback's numbers to ~1e-15 relative.
 *
 * Conventions are docs/design.md's; the terms are docs/estimator.md's. All arrays are
 * C-contiguous, caller-owned; nothing is allocated. Complex numbers are stored as (re, im)
 * pairs of doubles (numpy complex128's layout).
 */
#include "yaw_eval.h"

#include <math.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#define TWO_PI 6.283185307179586
/* estimator/solver.py's SLOW_CAP */
#define SLOW_CAP 0.9

static double wrap_fast(double x)
{
    return x - TWO_PI * rint(x * (1.0 / TWO_PI));
}

/* capsheet_yaw_eval with the links' (cos γ, sin γ) given (cs, 2 n_links), or computed into work
 * when cs is NULL. */
static double yaw_eval_cs(const capsheet_yaw_t *p, const double *gamma, const double *cs,
                          double *grad, double *work);

double capsheet_yaw_eval(const capsheet_yaw_t *p, const double *gamma, double *grad,
                         double *work)
{
    return yaw_eval_cs(p, gamma, NULL, grad, work);
}

double capsheet_yaw_eval_cs(const capsheet_yaw_t *p, const double *gamma, const double *cs,
                            double *grad, double *work)
{
    return yaw_eval_cs(p, gamma, cs, grad, work);
}

void capsheet_link_cs(int64_t n, const double *gamma, double *cs)
{
    int64_t k;
    for (k = 0; k < n; ++k) {
        cs[2 * k] = cos(gamma[k]);
        cs[2 * k + 1] = sin(gamma[k]);
    }
}

static double yaw_eval_cs(const capsheet_yaw_t *p, const double *gamma, const double *cs_in,
                          double *grad, double *work)
{
    const int64_t U = p->n_units, K = p->n_roll, NP = p->n_pairs, nv = p->n_var;
    /* work: per unit t (8), A (2), C (2), n (3), inv (1), Y (3) = 19 doubles; per link
     * (cos γ, sin γ): a link is in up to two cells and has a roll residual, so its sine and
     * cosine are computed once here instead of up to three times below */
    double *wt = work;
    double *wA = wt + 8 * U, *wC = wA + 2 * U, *wn = wC + 2 * U, *winv = wn + 3 * U;
    double *wY = winv + U, *wcs_own = wY + 3 * U;
    const double *wcs = cs_in ? cs_in : wcs_own;
    double cost_loop = 0.0, cost_roll = 0.0, cost_pair = 0.0, cost_abs = 0.0;
    int64_t u, m, k;

    for (k = 0; k <= nv; ++k)
        grad[k] = 0.0;
    if (!cs_in)
        for (k = 0; k < p->n_links; ++k) {
            wcs_own[2 * k] = cos(gamma[k]);
            wcs_own[2 * k + 1] = sin(gamma[k]);
        }

    /* loop closure (eq. 4, xy) and the cells' normals */
    for (u = 0; u < U; ++u) {
        double tr[4], ti[4], rr = 0.0, ri = 0.0;
        for (m = 0; m < 4; ++m) {
            const double *cs = wcs + 2 * p->units[4 * u + m], c = p->c_loop[4 * u + m];
            tr[m] = c * cs[0];
            ti[m] = c * cs[1];
            rr += tr[m];
            ri += ti[m];
            wt[8 * u + 2 * m] = tr[m];
            wt[8 * u + 2 * m + 1] = ti[m];
        }
        cost_loop += rr * rr + ri * ri;
        for (m = 0; m < 4; ++m) /* Im(conj(t) r) */
            grad[p->unit_var[4 * u + m]] += tr[m] * ri - ti[m] * rr;
        {
            /* D = t * (1, 1, -1, -1); A = D1 + D3, C = D0 + D2 */
            const double Ar = tr[1] - tr[3], Ai = ti[1] - ti[3];
            const double Cr = tr[0] - tr[2], Ci = ti[0] - ti[2];
            const double Az = p->Az[u], Cz = p->Cz[u];
            /* m_xy = i (Az C - Cz A), m_z = Im(conj(A) C) */
            const double pr = Az * Cr - Cz * Ar, pi = Az * Ci - Cz * Ai;
            const double mr = -pi, mi = pr;
            const double mz = Ar * Ci - Ai * Cr;
            const double mm = sqrt(mr * mr + mi * mi + mz * mz);
            const double inv = mm > 1e-9 ? 1.0 / mm : 0.0;
            wA[2 * u] = Ar;
            wA[2 * u + 1] = Ai;
            wC[2 * u] = Cr;
            wC[2 * u + 1] = Ci;
            wn[3 * u] = mr * inv;
            wn[3 * u + 1] = mi * inv;
            wn[3 * u + 2] = mz * inv;
            winv[u] = inv;
            wY[3 * u] = wY[3 * u + 1] = wY[3 * u + 2] = 0.0;
        }
    }

    /* roll residuals w (y_k . N_k); their gradient in reverse mode (see _roll_grad) */
    for (k = 0; k < K; ++k) {
        const int64_t c0 = p->roll_c0[k], c1 = p->roll_c1[k];
        const double ws1 = p->roll_ws1[k];
        const double *cs = wcs + 2 * p->roll_links[k], cg = cs[0], sg = cs[1];
        const double yr = p->y_c[2 * k] * cg - p->y_c[2 * k + 1] * sg;
        const double yi = p->y_c[2 * k] * sg + p->y_c[2 * k + 1] * cg;
        const double yz = p->y_z[k], w = p->w[k];
        const double Nr = wn[3 * c0] + ws1 * wn[3 * c1];
        const double Ni = wn[3 * c0 + 1] + ws1 * wn[3 * c1 + 1];
        const double Nz = wn[3 * c0 + 2] + ws1 * wn[3 * c1 + 2];
        /* conj(y) N */
        const double yNr = yr * Nr + yi * Ni, yNi = yr * Ni - yi * Nr;
        const double res = w * (yNr + yz * Nz);
        const double rho = w * res, r1 = ws1 * rho;
        cost_roll += res * res;
        grad[p->roll_var0[k]] += rho * yNi;
        wY[3 * c0] += rho * yr;
        wY[3 * c0 + 1] += rho * yi;
        wY[3 * c0 + 2] += rho * yz;
        wY[3 * c1] += r1 * yr;
        wY[3 * c1 + 1] += r1 * yi;
        wY[3 * c1 + 2] += r1 * yz;
    }

    /* Q = (Y - (Y.n) n) / |m|; gradient through the normals, Q . dm/dγ per link of the cell */
    for (u = 0; u < U; ++u) {
        const double *t = wt + 8 * u;
        const double nr = wn[3 * u], ni = wn[3 * u + 1], nz = wn[3 * u + 2], inv = winv[u];
        const double Yr = wY[3 * u], Yi = wY[3 * u + 1], Yz = wY[3 * u + 2];
        const double Yn = Yr * nr + Yi * ni + Yz * nz;
        const double Qr = (Yr - Yn * nr) * inv, Qi = (Yi - Yn * ni) * inv;
        const double Qz = (Yz - Yn * nz) * inv;
        const double Az = p->Az[u], Cz = p->Cz[u];
        const double fac[4] = {-Az, Cz, -Az, Cz};
        const double sgn[4] = {1.0, 1.0, -1.0, -1.0};
        const double zs[4] = {1.0, -1.0, 1.0, -1.0};
        for (m = 0; m < 4; ++m) {
            const double Dr = sgn[m] * t[2 * m], Di = sgn[m] * t[2 * m + 1];
            const double *X = (m & 1) ? wC + 2 * u : wA + 2 * u; /* A, C, A, C */
            const double dmr = Dr * fac[m], dmi = Di * fac[m];
            const double dmz = (X[0] * Dr + X[1] * Di) * zs[m];
            grad[p->unit_var[4 * u + m]] += Qr * dmr + Qi * dmi + Qz * dmz;
        }
    }

    /* prior pairs: λ (wrap(γ_k − γ_l − δ))² */
    for (k = 0; k < NP; ++k) {
        const double e = wrap_fast(gamma[p->pairs[2 * k]] - gamma[p->pairs[2 * k + 1]]
                                   - p->pair_t[k]);
        const double wb = p->lam_b[k] * e;
        cost_pair += wb * e;
        grad[p->pair_var[2 * k]] += wb;
        grad[p->pair_var[2 * k + 1]] -= wb;
    }

    /* yaw prior towards the target (only when some weight exceeds the floor) */
    if (p->abs_prior) {
        for (k = 0; k < nv; ++k) {
            const double e = wrap_fast(gamma[p->var_links[k]] - p->target[k]);
            cost_abs += p->lam[k] * e * e;
            grad[k] += p->lam[k] * e;
        }
    }
    return 0.5 * (cost_loop + cost_roll + cost_pair + cost_abs);
}

void capsheet_directions(int64_t n, const double *trig, const double *gamma, double *d,
                         double *nrm)
{
    int64_t k;
    for (k = 0; k < n; ++k) {
        const double ca = trig[4 * k], sa = trig[4 * k + 1], cb = trig[4 * k + 2];
        const double sb = trig[4 * k + 3];
        const double cg = cos(gamma[k]), sg = sin(gamma[k]);
        d[3 * k] = cg * cb;
        d[3 * k + 1] = sg * cb;
        d[3 * k + 2] = -sb;
        nrm[3 * k] = cg * sb * ca + sg * sa;
        nrm[3 * k + 1] = sg * sb * ca - cg * sa;
        nrm[3 * k + 2] = cb * ca;
    }
}

void capsheet_directions_cs(int64_t n, const double *trig, const double *cs, double *d,
                            double *nrm)
{
    int64_t k;
    for (k = 0; k < n; ++k) {
        const double ca = trig[4 * k], sa = trig[4 * k + 1], cb = trig[4 * k + 2];
        const double sb = trig[4 * k + 3];
        const double cg = cs[2 * k], sg = cs[2 * k + 1];
        d[3 * k] = cg * cb;
        d[3 * k + 1] = sg * cb;
        d[3 * k + 2] = -sb;
        nrm[3 * k] = cg * sb * ca + sg * sa;
        nrm[3 * k + 1] = sg * sb * ca - cg * sa;
        nrm[3 * k + 2] = cb * ca;
    }
}

double capsheet_eq8(int64_t n_units, const int64_t *units, const double *d, const double *nrm)
{
    double tot = 0.0;
    int64_t u, c;
    for (u = 0; u < n_units; ++u) {
        const int64_t *l = units + 4 * u;
        for (c = 0; c < 3; ++c) {
            const double rd = d[3 * l[0] + c] + d[3 * l[1] + c] - d[3 * l[2] + c] - d[3 * l[3] + c];
            const double rn = nrm[3 * l[0] + c] - nrm[3 * l[1] + c] + nrm[3 * l[2] + c]
                              - nrm[3 * l[3] + c];
            tot += rd * rd + rn * rn;
        }
    }
    return tot;
}

void capsheet_solvability(int64_t n_units, const int64_t *units, const double *trig,
                          double *ratio)
{
    static const double sa_sign[3] = {-1.0, 1.0, 1.0}, sb_sign[3] = {1.0, -1.0, 1.0};
    int64_t u;
    int m;
    for (u = 0; u < n_units; ++u) {
        const int64_t *l = units + 4 * u;
        double A = 0.0, B = 0.0, Cr = 0.0, Ci = 0.0;
        const double *t0 = trig + 4 * l[0];
        int finite = isfinite(t0[0]) && isfinite(t0[2]);
        for (m = 1; m < 4; ++m) {
            const double *t = trig + 4 * l[m];
            const double ca = t[0], sa = t[1], cb = t[2], sb = t[3];
            const double a = cb * sa_sign[m - 1];
            const double br = sb * ca * sb_sign[m - 1], bi = -sa * sb_sign[m - 1];
            finite = finite && isfinite(ca) && isfinite(cb);
            A += a * a;
            B += br * br + bi * bi;
            Cr += a * br;
            Ci += a * bi;
        }
        if (!finite) {
            ratio[u] = NAN;
        } else {
            const double half = 0.5 * (A + B);
            const double q = 0.25 * (A - B) * (A - B) + (Cr * Cr + Ci * Ci);
            const double disc = sqrt(q > 0.0 ? q : 0.0);
            const double mu1 = half + disc, mu2 = half - disc > 0.0 ? half - disc : 0.0;
            ratio[u] = mu1 > 0.0 ? sqrt(mu2 / mu1) : 0.0;
        }
    }
}

void capsheet_flatness(int64_t rows_u, int64_t cols_u, const int64_t *units, const double *r,
                       const double *norm_g, double g0, int64_t radius, double th0, double *th2,
                       double *tmp, double *h)
{
    const int64_t nu = rows_u * cols_u, k = 2 * radius + 1;
    int64_t u, i, j, q;
    int m;
    for (u = 0; u < nu; ++u) { /* θ² per unit: twice the mean of 1 − cos(tilt) of its links */
        double s = 0.0;
        for (m = 0; m < 4; ++m) {
            const int64_t l = units[4 * u + m];
            const double den = norm_g[l] * g0;
            s += 1.0 - r[3 * l + 2] / (den > 1e-300 ? den : 1e-300);
        }
        th2[u] = 2.0 * (s / 4.0);
    }
    /* the (2 radius + 1)² box mean, edges extended by their nearest value (scipy's
     * uniform_filter, mode "nearest"): along the rows, then along the columns */
    for (i = 0; i < rows_u; ++i)
        for (j = 0; j < cols_u; ++j) {
            double s = 0.0;
            for (q = i - radius; q <= i + radius; ++q) {
                const int64_t qq = q < 0 ? 0 : (q >= rows_u ? rows_u - 1 : q);
                s += th2[qq * cols_u + j];
            }
            tmp[i * cols_u + j] = s / (double)k;
        }
    for (i = 0; i < rows_u; ++i)
        for (j = 0; j < cols_u; ++j) {
            double s = 0.0;
            for (q = j - radius; q <= j + radius; ++q) {
                const int64_t qq = q < 0 ? 0 : (q >= cols_u ? cols_u - 1 : q);
                s += tmp[i * cols_u + qq];
            }
            s /= (double)k;
            h[i * cols_u + j] = exp(-(s > 0.0 ? s : 0.0) / (th0 * th0));
        }
}

void capsheet_yaw_coeffs(int64_t n_units, const int64_t *units, int64_t n_roll,
                         const int64_t *roll_links, const double *trig, double *c_loop,
                         double *Az, double *Cz, double *y_c, double *y_z)
{
    static const double s_d[4] = {1.0, 1.0, -1.0, -1.0};
    int64_t u, k;
    int m;
    for (u = 0; u < n_units; ++u) {
        double sbm[4];
        for (m = 0; m < 4; ++m) {
            const double *t = trig + 4 * units[4 * u + m];
            c_loop[4 * u + m] = t[2] * s_d[m];
            sbm[m] = t[3];
        }
        Az[u] = -(sbm[1] + sbm[3]);
        Cz[u] = -(sbm[0] + sbm[2]);
    }
    for (k = 0; k < n_roll; ++k) {
        const double *t = trig + 4 * roll_links[k];
        const double sa = t[1];
        y_c[2 * k] = t[3] * sa;
        y_c[2 * k + 1] = t[0];
        y_z[k] = t[2] * sa;
    }
}

void capsheet_angle_trig(int64_t n, const double *alpha, const double *beta, double *trig)
{
    int64_t k;
    for (k = 0; k < n; ++k) {
        trig[4 * k] = cos(alpha[k]);
        trig[4 * k + 1] = sin(alpha[k]);
        trig[4 * k + 2] = cos(beta[k]);
        trig[4 * k + 3] = sin(beta[k]);
    }
}

void capsheet_reading_trig(int64_t n, const double *r, const double *alpha, const double *beta,
                           double *trig)
{
    int64_t k;
    for (k = 0; k < n; ++k) {
        const double x = r[3 * k], y = r[3 * k + 1], z = r[3 * k + 2];
        const double h2 = y * y + z * z, h = sqrt(h2), m = sqrt(h2 + x * x);
        if (h > 1e-150 && m < 1e150) {  /* cos, sin of the atan2s from the ratios */
            trig[4 * k] = z / h;
            trig[4 * k + 1] = y / h;
            trig[4 * k + 2] = h / m;
            trig[4 * k + 3] = -x / m;
        } else {  /* on the x axis (atan2's signed zeros decide), extreme, or not finite */
            trig[4 * k] = cos(alpha[k]);
            trig[4 * k + 1] = sin(alpha[k]);
            trig[4 * k + 2] = cos(beta[k]);
            trig[4 * k + 3] = sin(beta[k]);
        }
    }
}

/* The lane sums a_c[l] += Σ b_c[i] g[i] over i ≡ l (mod 4), i < nb rounded down to a multiple
 * of 4, for four float columns b0..b3 against g; returns that bound. SSE2 (every x86-64) adds
 * the same products in the same order as the plain loop, so results do not depend on it. */
static int64_t dot4x4(int64_t nb, const float *restrict b0, const float *restrict b1,
                      const float *restrict b2, const float *restrict b3,
                      const double *restrict g, double *a0, double *a1, double *a2, double *a3)
{
    int64_t i = 0;
#if defined(__SSE2__)
    __m128d s[8];
    const float *b[4];
    double *a[4];
    int c;
    b[0] = b0; b[1] = b1; b[2] = b2; b[3] = b3;
    a[0] = a0; a[1] = a1; a[2] = a2; a[3] = a3;
    for (c = 0; c < 8; ++c)
        s[c] = _mm_setzero_pd();
    for (; i + 4 <= nb; i += 4) {
        const __m128d g01 = _mm_loadu_pd(g + i), g23 = _mm_loadu_pd(g + i + 2);
        for (c = 0; c < 4; ++c) {
            const __m128 f = _mm_loadu_ps(b[c] + i);
            s[2 * c] = _mm_add_pd(s[2 * c], _mm_mul_pd(_mm_cvtps_pd(f), g01));
            s[2 * c + 1] = _mm_add_pd(s[2 * c + 1], _mm_mul_pd(_mm_cvtps_pd(_mm_movehl_ps(f, f)),
                                                               g23));
        }
    }
    for (c = 0; c < 4; ++c) {
        _mm_storeu_pd(a[c], s[2 * c]);
        _mm_storeu_pd(a[c] + 2, s[2 * c + 1]);
    }
#else
    int l;
    for (; i + 4 <= nb; i += 4)
        for (l = 0; l < 4; ++l) {
            const double gi = g[i + l];
            a0[l] += b0[i + l] * gi;
            a1[l] += b1[i + l] * gi;
            a2[l] += b2[i + l] * gi;
            a3[l] += b3[i + l] * gi;
        }
#endif
    return i;
}

/* Supernodal L D Lᵀ solve; see yaw_eval.h. Forward: per supernode the unit lower diagonal block
 * (column axpys), then its below-rows accumulated column by column into `t` (contiguous axpys the
 * compiler vectorises) and subtracted from x once. Backward: the below rows gathered into `t`,
 * four columns' dot products at a time (four independent sums: no reassociation), then the
 * diagonal block transposed. */
void capsheet_ldl_solve(int64_t n, int64_t n_super, const int32_t *sn_col, const int64_t *sn_row,
                        const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                        const float *val, const double *diag, double *x, double *work)
{
    int64_t s, j;
    for (s = 0; s < n_super; ++s) {
        const int64_t c0 = sn_col[s], w = sn_col[s + 1] - c0;
        const int64_t nb = sn_row[s + 1] - sn_row[s];
        const int32_t *restrict r = rows + sn_row[s];
        const float *restrict dg = val + sn_diag[s];
        const float *restrict bl = val + sn_below[s];
        double *restrict xs = x + c0;
        int64_t k, i;
        for (k = 0; k + 1 < w; ++k) {
            const double xk = xs[k];
            for (i = k + 1; i < w; ++i)
                xs[i] -= dg[k * w + i] * xk;
        }
        if (nb == 0)
            continue;
        if (w == 1) {
            const double x0 = xs[0];
            for (i = 0; i < nb; ++i)
                x[r[i]] -= bl[i] * x0;
            continue;
        }
        {
            double *restrict t = work;
            for (i = 0; i < nb; ++i)
                t[i] = 0.0;
            for (k = 0; k + 4 <= w; k += 4) {  /* four columns per pass over t */
                const double x0 = xs[k], x1 = xs[k + 1], x2 = xs[k + 2], x3 = xs[k + 3];
                const float *restrict b0 = bl + k * nb, *restrict b1 = b0 + nb;
                const float *restrict b2 = b1 + nb, *restrict b3 = b2 + nb;
                for (i = 0; i < nb; ++i)
                    t[i] += (b0[i] * x0 + b1[i] * x1) + (b2[i] * x2 + b3[i] * x3);
            }
            for (; k < w; ++k) {
                const double xk = xs[k];
                const float *restrict b = bl + k * nb;
                for (i = 0; i < nb; ++i)
                    t[i] += b[i] * xk;
            }
            for (i = 0; i < nb; ++i)
                x[r[i]] -= t[i];
        }
    }
    for (j = 0; j < n; ++j)
        x[j] /= diag[j];
    for (s = n_super - 1; s >= 0; --s) {
        const int64_t c0 = sn_col[s], w = sn_col[s + 1] - c0;
        const int64_t nb = sn_row[s + 1] - sn_row[s];
        const int32_t *restrict r = rows + sn_row[s];
        const float *restrict dg = val + sn_diag[s];
        const float *restrict bl = val + sn_below[s];
        double *restrict xs = x + c0;
        double *restrict g = work;
        int64_t k, i;
        if (nb > 0) {
            for (i = 0; i < nb; ++i)
                g[i] = x[r[i]];
            for (k = 0; k + 4 <= w; k += 4) {
                const float *restrict b0 = bl + k * nb, *restrict b1 = b0 + nb;
                const float *restrict b2 = b1 + nb, *restrict b3 = b2 + nb;
                /* four columns' dot products, each in four lanes (i mod 4) summed at the end:
                 * sixteen independent sums in the same order with SSE2 and without */
                double a0[4] = {0.0, 0.0, 0.0, 0.0}, a1[4] = {0.0, 0.0, 0.0, 0.0};
                double a2[4] = {0.0, 0.0, 0.0, 0.0}, a3[4] = {0.0, 0.0, 0.0, 0.0};
                i = dot4x4(nb, b0, b1, b2, b3, g, a0, a1, a2, a3);
                for (; i < nb; ++i) {
                    const double gi = g[i];
                    a0[0] += b0[i] * gi;
                    a1[0] += b1[i] * gi;
                    a2[0] += b2[i] * gi;
                    a3[0] += b3[i] * gi;
                }
                xs[k] -= (a0[0] + a0[1]) + (a0[2] + a0[3]);
                xs[k + 1] -= (a1[0] + a1[1]) + (a1[2] + a1[3]);
                xs[k + 2] -= (a2[0] + a2[1]) + (a2[2] + a2[3]);
                xs[k + 3] -= (a3[0] + a3[1]) + (a3[2] + a3[3]);
            }
            for (; k < w; ++k) {
                const float *restrict b0 = bl + k * nb;
                double a0[4] = {0.0, 0.0, 0.0, 0.0};
                int l;
                for (i = 0; i + 4 <= nb; i += 4)
                    for (l = 0; l < 4; ++l)
                        a0[l] += b0[i + l] * g[i + l];
                for (; i < nb; ++i)
                    a0[0] += b0[i] * g[i];
                xs[k] -= (a0[0] + a0[1]) + (a0[2] + a0[3]);
            }
        }
        for (k = w - 2; k >= 0; --k) {
            double a = 0.0;
            for (i = k + 1; i < w; ++i)
                a += dg[k * w + i] * xs[i];
            xs[k] -= a;
        }
    }
}

void capsheet_ldl_fill(int64_t n_super, const int32_t *l_ptr, const int32_t *l_idx,
                       const double *l_val, const int32_t *sn_col, const int64_t *sn_row,
                       const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                       int32_t *map, float *val)
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
                    val[sn_diag[s] + k * w + (i - c0)] = (float)l_val[p];
                else if (map[i] >= 0)
                    val[sn_below[s] + k * nb + map[i]] = (float)l_val[p];
            }
        }
        for (q = 0; q < nb; ++q)
            map[r[q]] = -1;
    }
}

/* estimator/solver.py's step_converged: whether a step of largest entry smax (the last one's
 * prev, INFINITY when none; accelerated: the last move was an Anderson one) ends the iteration. */
static int capsheet_step_converged(double smax, double prev, int32_t accelerated, double tol,
                                   double predict_within, double slow)
{
    if (slow > 0.0) {  /* a slow step passed on this factorisation: its mode may be left */
        double rho = isfinite(prev) && prev > 0.0 ? smax / prev : 0.0;
        rho = rho > slow ? rho : slow;
        rho = rho < SLOW_CAP ? rho : SLOW_CAP;
        return smax * rho < tol * (1.0 - rho);
    }
    if (isfinite(prev) && !accelerated && smax < prev && smax < predict_within * tol) {
        const double rho = smax / prev;
        return smax * rho < tol * (rho > 0.5 ? 1.0 - rho : 1.0);
    }
    return smax < tol;
}

/* cs_out = (cos, sin) of gamma + move per link (cs_in: gamma's; move on the variables' links):
 * each variable's pair turned by its move, e^{iδ} by its Taylor series where |δ| <= 1/8 (twelve
 * terms: the rest is below 1e-19, under the rounding of cos and sin themselves), else by cos and
 * sin. A chord step's moves are small: a cos and a sin per link were half an evaluation. */
static void turn_cs(int64_t n_links, int64_t nv, const int64_t *var_links, const double *move,
                    const double *cs_in, double *cs_out)
{
    int64_t k;
    for (k = 0; k < 2 * n_links; ++k)
        cs_out[k] = cs_in[k];
    for (k = 0; k < nv; ++k) {
        const double d = move[k], d2 = d * d;
        const int64_t l = var_links[k];
        const double c0 = cs_in[2 * l], s0 = cs_in[2 * l + 1];
        double cd, sd;
        if (fabs(d) <= 0.125) {
            cd = 1.0 - d2 * (1.0 / 2.0 - d2 * (1.0 / 24.0 - d2 * (1.0 / 720.0 - d2 * (1.0 / 40320.0
                 - d2 * (1.0 / 3628800.0)))));
            sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0 - d2 * (1.0 / 5040.0 - d2 * (1.0 / 362880.0
                 - d2 * (1.0 / 39916800.0))))));
        } else {
            cd = cos(d);
            sd = sin(d);
        }
        cs_out[2 * l] = c0 * cd - s0 * sd;
        cs_out[2 * l + 1] = s0 * cd + c0 * sd;
    }
}

/* The chord iterations of estimator/solver.py's solve_global for one snapshot on a factorisation
 * kept from before (no damping): see yaw_eval.h. Each iteration: the step −A⁻¹ grad (the
 * supernodal solve on the structure's ordering), the Anderson move when the step reverses the
 * last, the convergence test, the cost at the new point (the plain step instead when an
 * accelerated move raised it), acceptance, the refactorisation test. */
int32_t capsheet_chord(const capsheet_yaw_t *p, double *gamma, double *cost, double *grad,
                       const capsheet_chord_t *c, int64_t *iterations, double *prev_smax,
                       double *steps, double *work)
{
    const int64_t nv = p->n_var, n_links = c->n_links;
    double *step = work, *move = step + nv, *s_prev = move + nv, *dx = s_prev + nv;
    double *x = dx + nv, *g_new = x + nv, *grad_new = g_new + n_links;
    double *ldl_work = grad_new + nv + 1, *eval_work = ldl_work + c->ldl_work_size;
    double *cs = c->cs_out;  /* the current point's (cos γ, sin γ), handed back with it */
    double *cs_new = eval_work + 19 * (p->n_units > 0 ? p->n_units : 1) + 2 * n_links;
    int32_t has_hist = 0, accelerated = 0;
    int64_t it = *iterations, k, poor = 0;
    double slow = 0.0;  /* the slowest contraction of a slow step passed (not refactorised) */
    const int64_t it0 = it;
    double ps = *prev_smax, cst = *cost;
    steps[0] = steps[1] = 0.0;
    for (k = 0; k < 2 * n_links; ++k)
        cs[k] = c->cs_in[k];
    while (it < c->max_iter) {
        double smax = 0.0, cost_new;
        int32_t acc = 0;
        ++it;
        for (k = 0; k < nv; ++k)
            x[k] = -grad[c->perm_inv[k]];
        capsheet_ldl_solve(nv, c->n_super, c->sn_col, c->sn_row, c->rows, c->sn_diag,
                           c->sn_below, c->val, c->diag, x, ldl_work);
        for (k = 0; k < nv; ++k) {
            const double s = x[c->perm_of_var[k]];
            step[k] = s;
            if (fabs(s) > smax)
                smax = fabs(s);
        }
        if (has_hist) {  /* Anderson, one step of history, only on a reversing step */
            double ss = 0.0, pp = 0.0, sp = 0.0;
            for (k = 0; k < nv; ++k) {
                ss += step[k] * step[k];
                pp += s_prev[k] * s_prev[k];
                sp += step[k] * s_prev[k];
            }
            if (ss * pp > 0.0 && sp < c->anderson_cos * sqrt(ss * pp)) {
                double num = 0.0, den = 0.0;
                for (k = 0; k < nv; ++k) {
                    const double d = step[k] - s_prev[k];
                    num += d * step[k];
                    den += d * d;
                }
                if (den > 0.0) {
                    const double th = num / den;
                    if (th > 0.0 && th < 1.0) {
                        for (k = 0; k < nv; ++k)
                            move[k] = step[k] - th * (dx[k] + (step[k] - s_prev[k]));
                        acc = 1;
                    }
                }
            }
        }
        if (!acc)
            for (k = 0; k < nv; ++k)
                move[k] = step[k];
        for (k = 0; k < n_links; ++k)
            g_new[k] = gamma[k];
        for (k = 0; k < nv; ++k)
            g_new[p->var_links[k]] += move[k];
        if (it - it0 <= 2)
            steps[it - it0 - 1] = smax;
        if (capsheet_step_converged(smax, ps, accelerated, c->tol, c->predict_within, slow)
            || (it == it0 + 1 && c->chain_safety > 0.0
                && c->chain_safety * fmax(c->chain_rho * smax, c->chain_kappa * smax * smax) < c->tol)) {
            for (k = 0; k < n_links; ++k)
                gamma[k] = g_new[k];
            turn_cs(n_links, nv, p->var_links, move, cs, cs_new);
            for (k = 0; k < 2 * n_links; ++k)
                cs[k] = cs_new[k];
            *iterations = it;
            *cost = cst;
            return 0;
        }
        turn_cs(n_links, nv, p->var_links, move, cs, cs_new);
        cost_new = yaw_eval_cs(p, g_new, cs_new, grad_new, eval_work);
        if (acc && !(cost_new <= cst * (1.0 + 1e-12) + 1e-300)) {
            acc = 0;
            for (k = 0; k < nv; ++k)
                move[k] = step[k];
            for (k = 0; k < n_links; ++k)
                g_new[k] = gamma[k];
            for (k = 0; k < nv; ++k)
                g_new[p->var_links[k]] += move[k];
            turn_cs(n_links, nv, p->var_links, move, cs, cs_new);
            cost_new = yaw_eval_cs(p, g_new, cs_new, grad_new, eval_work);
        }
        if (!(cost_new <= cst * (1.0 + 1e-12) + 1e-300)) {
            *iterations = it;
            *cost = cst;
            *prev_smax = ps;
            return 1;  /* refactorise at gamma (unchanged) */
        }
        for (k = 0; k < n_links; ++k)
            gamma[k] = g_new[k];
        for (k = 0; k <= nv; ++k)
            grad[k] = grad_new[k];
        for (k = 0; k < 2 * n_links; ++k)
            cs[k] = cs_new[k];
        cst = cost_new;
        for (k = 0; k < nv; ++k) {
            s_prev[k] = step[k];
            dx[k] = move[k];
        }
        has_hist = 1;
        accelerated = acc;
        if (!(smax > c->refactor_ratio * ps))
            poor = 0;
        else if (smax < c->refactor_far * c->tol || smax > c->refactor_growth * ps
                 || ++poor >= c->refactor_patience) {
            *iterations = it;
            *cost = cst;
            *prev_smax = smax;
            return 2;  /* accepted; refactorise at the new gamma */
        } else {
            const double r = smax / ps;
            slow = r > slow ? r : slow;
        }
        ps = smax;
    }
    *iterations = it;
    *cost = cst;
    *prev_smax = ps;
    return 3;
}
