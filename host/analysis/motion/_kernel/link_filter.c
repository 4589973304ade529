/* See link_filter.h. */
#include "link_filter.h"
#include "link_internal.h"

#include <math.h>

/* th^2 below which `rodrigues` takes its series (th < 0.05 rad) */
#define RODRIGUES_SERIES 2.5e-3

static inline void rodrigues(const double *v, double *out)
{
    double x = v[0], y = v[1], z = v[2];
    double th2 = x * x + y * y + z * z;
    double a, b;
    if (th2 < 1e-12) {
        a = 1.0 - th2 / 6.0;
        b = 0.5 - th2 / 24.0;
    } else if (th2 < RODRIGUES_SERIES) {
        /* sin(th)/th and (1 - cos th)/th^2 by their series to th^8: the first term left out is
         * below 3e-21 (th2^5/11!, th2^5/12!), under a unit in the last place of a and b; a
         * propagation's or a correction's angle (~1e-2 rad and less) always takes this branch,
         * and it costs a fifth of sin and cos */
        double ta = 1.0 - th2 * (1.0 / 42.0) * (1.0 - th2 * (1.0 / 72.0));
        double tb = 1.0 - th2 * (1.0 / 56.0) * (1.0 - th2 * (1.0 / 90.0));
        a = 1.0 - th2 * (1.0 / 6.0) * (1.0 - th2 * (1.0 / 20.0) * ta);
        b = 0.5 - th2 * (1.0 / 24.0) * (1.0 - th2 * (1.0 / 30.0) * tb);
    } else {
        double th = sqrt(th2);
        a = sin(th) / th;
        b = (1.0 - cos(th)) / th2;
    }
    double xx = x * x, yy = y * y, zz = z * z, xy = x * y, xz = x * z, yz = y * z;
    out[0] = 1.0 - b * (yy + zz);
    out[4] = 1.0 - b * (xx + zz);
    out[8] = 1.0 - b * (xx + yy);
    out[1] = b * xy - a * z;
    out[3] = b * xy + a * z;
    out[2] = b * xz + a * y;
    out[6] = b * xz - a * y;
    out[5] = b * yz - a * x;
    out[7] = b * yz + a * x;
}

static inline void mat3_mul(const double *A, const double *B, double *C)
{
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) {
            C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
        }
    }
}

void capsheet_mf_propagate(size_t n, double *R, double *P, const double *w0, const double *w1,
                           const double *dt, const double *q, const double *qb)
{
    for (size_t k = 0; k < n; k++) {
        const double *a = w0 + 3 * k, *b = w1 + 3 * k;
        double h = dt[k], h2 = h * h / 12.0;
        double d[3], E[9], Rn[9];
        d[0] = 0.5 * (a[0] + b[0]) * h + (a[1] * b[2] - a[2] * b[1]) * h2;
        d[1] = 0.5 * (a[1] + b[1]) * h + (a[2] * b[0] - a[0] * b[2]) * h2;
        d[2] = 0.5 * (a[2] + b[2]) * h + (a[0] * b[1] - a[1] * b[0]) * h2;
        rodrigues(d, E);
        double *Rk = R + 9 * k;
        mat3_mul(Rk, E, Rn);
        for (int i = 0; i < 9; i++) {
            Rk[i] = Rn[i];
        }
        /* G = R dt; Ptt' = Ptt - G Pbt - Ptb G^T + G Pbb G^T + q I; Ptb' = Ptb - G Pbb */
        double *Pk = P + 36 * k;
        double G[9], GPbb[9], GPbt[9], T[9];
        for (int i = 0; i < 9; i++) {
            G[i] = Rn[i] * h;
        }
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) {
                double s1 = 0.0, s2 = 0.0;
                for (int l = 0; l < 3; l++) {
                    s1 += G[3 * i + l] * Pk[6 * (3 + l) + 3 + j];
                    s2 += G[3 * i + l] * Pk[6 * (3 + l) + j];
                }
                GPbb[3 * i + j] = s1;
                GPbt[3 * i + j] = s2;
            }
        }
        for (int i = 0; i < 3; i++) { /* symmetric: the upper triangle, mirrored */
            for (int j = i; j < 3; j++) {
                double s = 0.0;
                for (int l = 0; l < 3; l++) {
                    s += GPbb[3 * i + l] * G[3 * j + l];
                }
                T[3 * i + j] = Pk[6 * i + j] - GPbt[3 * i + j] - GPbt[3 * j + i] + s;
                T[3 * j + i] = T[3 * i + j];
            }
        }
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) {
                Pk[6 * i + j] = T[3 * i + j] + (i == j ? q[k] : 0.0);
                double tb = Pk[6 * i + 3 + j] - GPbb[3 * i + j];
                Pk[6 * i + 3 + j] = tb;
            }
        }
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) {
                Pk[6 * (3 + j) + i] = Pk[6 * i + 3 + j];
            }
            Pk[6 * (3 + i) + 3 + i] += qb[k];
        }
    }
}

/* link_internal.h (the update and the consider step's update, consider_filter.c, share it) */
double capsheet_mf_accel_innovation(const double *Rk, const double *v, const double *fk,
                                    const double *Pk, double r2k, double *H, double *y,
                                    double *HP, double *Si)
{
    double Vx[9] = {0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0};
    double S[9];
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) {
            H[3 * i + j] = Rk[i] * Vx[j] + Rk[3 + i] * Vx[3 + j] + Rk[6 + i] * Vx[6 + j];
        }
        y[i] = fk[i] - (Rk[i] * v[0] + Rk[3 + i] * v[1] + Rk[6 + i] * v[2]);
    }
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 6; j++) {
            HP[6 * i + j] = H[3 * i] * Pk[j] + H[3 * i + 1] * Pk[6 + j] + H[3 * i + 2] * Pk[12 + j];
        }
    }
    for (int i = 0; i < 3; i++) { /* the upper triangle: all the cofactors read */
        for (int j = i; j < 3; j++) {
            S[3 * i + j] = HP[6 * i] * H[3 * j] + HP[6 * i + 1] * H[3 * j + 1]
                           + HP[6 * i + 2] * H[3 * j + 2] + (i == j ? r2k : 0.0);
        }
    }
    double a = S[0], b = S[1], c = S[2], d = S[4], e = S[5], ff = S[8];
    double A = d * ff - e * e, B = c * e - b * ff, C = b * e - c * d;
    double D = a * ff - c * c, E = b * c - a * e, F = a * d - b * b;
    double inv_det = 1.0 / (a * A + b * B + c * C);
    Si[0] = A * inv_det; Si[1] = B * inv_det; Si[2] = C * inv_det;
    Si[3] = B * inv_det; Si[4] = D * inv_det; Si[5] = E * inv_det;
    Si[6] = C * inv_det; Si[7] = E * inv_det; Si[8] = F * inv_det;
    double m2 = 0.0;
    for (int i = 0; i < 3; i++) {
        m2 += y[i] * (Si[3 * i] * y[0] + Si[3 * i + 1] * y[1] + Si[3 * i + 2] * y[2]);
    }
    return m2;
}

void capsheet_mf_accel(size_t n, const double *R, double *P, const double *f, const double *vec,
                       const double *r2, double gate, const uint8_t *valid, double *x,
                       double *nis)
{
    for (size_t k = 0; k < n; k++) {
        double *xk = x + 6 * k;
        if (!valid[k]) {
            for (int i = 0; i < 6; i++) {
                xk[i] = 0.0;
            }
            nis[k] = NAN;
            continue;
        }
        const double *Rk = R + 9 * k, *v = vec + 3 * k, *fk = f + 3 * k;
        double *Pk = P + 36 * k;
        double H[9], y[3], HP[18], Si[9];
        double m2 = capsheet_mf_accel_innovation(Rk, v, fk, Pk, r2[k], H, y, HP, Si);
        nis[k] = m2;
        double infl = m2 / gate > 1.0 ? m2 / gate : 1.0;
        for (int i = 0; i < 9; i++) {
            Si[i] /= infl;
        }
        /* K = HP^T Si (6 x 3); x = K y; P -= K HP */
        double K[18];
        for (int i = 0; i < 6; i++) {
            for (int j = 0; j < 3; j++) {
                K[3 * i + j] = HP[i] * Si[j] + HP[6 + i] * Si[3 + j] + HP[12 + i] * Si[6 + j];
            }
            xk[i] = K[3 * i] * y[0] + K[3 * i + 1] * y[1] + K[3 * i + 2] * y[2];
        }
        for (int i = 0; i < 6; i++) {
            for (int j = 0; j < 6; j++) {
                Pk[6 * i + j] -= K[3 * i] * HP[j] + K[3 * i + 1] * HP[6 + j] + K[3 * i + 2] * HP[12 + j];
            }
        }
    }
}

void capsheet_mf_yaw(size_t n, double *P, const double *mu, const double *a_diag, double *x)
{
    for (size_t k = 0; k < n; k++) {
        double *Pk = P + 36 * k;
        double c[6];
        for (int i = 0; i < 6; i++) {
            c[i] = Pk[6 * i + 2];
        }
        double p = c[2];
        double s = (1.0 - 1.0 / (a_diag[k] * p));
        for (int i = 0; i < 6; i++) {
            double g = c[i] / p;
            x[6 * k + i] = g * mu[k];
            for (int j = 0; j < 6; j++) {
                Pk[6 * i + j] -= g * (c[j] * s);
            }
        }
    }
}

void capsheet_mf_apply(size_t n, double *R, double *bias, double *P, const double *x)
{
    for (size_t k = 0; k < n; k++) {
        double E[9], Rn[9];
        rodrigues(x + 6 * k, E);
        double *Rk = R + 9 * k;
        mat3_mul(E, Rk, Rn);
        for (int i = 0; i < 9; i++) {
            Rk[i] = Rn[i];
        }
        for (int i = 0; i < 3; i++) {
            bias[3 * k + i] += x[6 * k + 3 + i];
        }
        double *Pk = P + 36 * k;
        for (int i = 0; i < 6; i++) {
            for (int j = i + 1; j < 6; j++) {
                double s = 0.5 * (Pk[6 * i + j] + Pk[6 * j + i]);
                Pk[6 * i + j] = s;
                Pk[6 * j + i] = s;
            }
        }
    }
}

void capsheet_mf_lattice(size_t n, size_t n_units, size_t n_pairs, size_t nnz, const double *R,
                         const double *P, const int32_t *units, const int32_t *pair_link,
                         const int32_t *pair_cell, const double *inv_ncell,
                         const int32_t *jac_slots, const int32_t *jac_indptr,
                         const int32_t *jac_indices, double floor2, double *res, double *wts,
                         double *jd, double *lat_diag, double *work)
{
    size_t U = n_units;
    double *A = work, *C = work + 3 * U, *nc = work + 6 * U, *inv_nN = work + 9 * U;
    double *nbar = work + 10 * U;
    const double sign[4] = {1.0, 1.0, -1.0, -1.0};
    size_t e = 0; /* the running index into jac_slots */
    for (size_t i = 0; i < nnz; i++) {
        jd[i] = 0.0;
    }
    for (size_t u = 0; u < U; u++) {
        const int32_t *un = units + 4 * u;
        const double *d0 = R + 9 * un[0], *d1 = R + 9 * un[1], *d2 = R + 9 * un[2],
                     *d3 = R + 9 * un[3]; /* d = R[:, :, 0]: elements 0, 3, 6 */
        res[2 * u] = d0[0] + d1[0] - d2[0] - d3[0];
        res[2 * u + 1] = d0[3] + d1[3] - d2[3] - d3[3];
        for (int c = 0; c < 2; c++) {
            for (int s = 0; s < 4; s++) {
                const double *dk = R + 9 * un[s];
                double ez = c == 0 ? -dk[3] : dk[0]; /* e_z x d, x then y */
                jd[jac_slots[e++]] += sign[s] * ez;
            }
        }
        double *a = A + 3 * u, *cc = C + 3 * u;
        for (int i = 0; i < 3; i++) {
            a[i] = d1[3 * i] + d3[3 * i];
            cc[i] = d0[3 * i] + d2[3 * i];
        }
        double N0 = a[1] * cc[2] - a[2] * cc[1];
        double N1 = a[2] * cc[0] - a[0] * cc[2];
        double N2 = a[0] * cc[1] - a[1] * cc[0];
        double nN = sqrt(N0 * N0 + N1 * N1 + N2 * N2);
        double inv = nN > 0.1 ? 1.0 / nN : 0.0; /* a squashed cell has no normal */
        inv_nN[u] = inv;
        nc[3 * u] = N0 * inv;
        nc[3 * u + 1] = N1 * inv;
        nc[3 * u + 2] = N2 * inv;
    }
    /* each link's mean normal over its cells (pairs are ordered by link, then cell) */
    for (size_t k = 0; k < 3 * n; k++) {
        nbar[k] = 0.0;
    }
    for (size_t p = 0; p < n_pairs; p++) {
        int32_t k = pair_link[p], u = pair_cell[p];
        for (int i = 0; i < 3; i++) {
            nbar[3 * k + i] += inv_ncell[k] * nc[3 * u + i];
        }
    }
    for (size_t k = 0; k < n; k++) {
        const double *Rk = R + 9 * k, *nb = nbar + 3 * k;
        double Y0 = Rk[1], Y1 = Rk[4], Y2 = Rk[7];
        res[2 * U + k] = Y0 * nb[0] + Y1 * nb[1] + Y2 * nb[2];
        jd[jac_slots[e++]] += Y0 * nb[1] - Y1 * nb[0];
    }
    for (size_t p = 0; p < n_pairs; p++) {
        int32_t k = pair_link[p], u = pair_cell[p];
        const double *Rk = R + 9 * k, *n3 = nc + 3 * u, *a = A + 3 * u, *cc = C + 3 * u;
        double Y[3] = {Rk[1], Rk[4], Rk[7]};
        double t = n3[0] * Y[0] + n3[1] * Y[1] + n3[2] * Y[2];
        double sc = inv_nN[u] * inv_ncell[k];
        double W[3];
        for (int i = 0; i < 3; i++) {
            W[i] = (Y[i] - n3[i] * t) * sc;
        }
        double CxW[3] = {cc[1] * W[2] - cc[2] * W[1], cc[2] * W[0] - cc[0] * W[2],
                         cc[0] * W[1] - cc[1] * W[0]};
        double WxA[3] = {W[1] * a[2] - W[2] * a[1], W[2] * a[0] - W[0] * a[2],
                         W[0] * a[1] - W[1] * a[0]};
        const int32_t *un = units + 4 * u;
        for (int s = 0; s < 4; s++) {
            const double *dk = R + 9 * un[s];
            const double *v = (s == 0 || s == 2) ? WxA : CxW;
            double ez0 = -dk[3], ez1 = dk[0];
            jd[jac_slots[e++]] += ez0 * v[0] + ez1 * v[1] + 0.0 * v[2];
        }
    }
    /* weights: the tilt variance of the links involved plus the model's floor */
    for (size_t u = 0; u < U; u++) {
        const int32_t *un = units + 4 * u;
        double s = 0.0;
        for (int i = 0; i < 4; i++) {
            const double *Pk = P + 36 * un[i];
            s += Pk[0] + Pk[7];
        }
        double w = 1.0 / (s + floor2);
        wts[2 * u] = w;
        wts[2 * u + 1] = w;
    }
    for (size_t k = 0; k < n; k++) {
        const double *Pk = P + 36 * k;
        wts[2 * U + k] = 1.0 / (2.0 * (Pk[0] + Pk[7]) + floor2);
        lat_diag[k] = 0.0;
    }
    (void)nnz;
    for (size_t r = 0; r < 2 * U + n; r++) { /* the entries in CSR order, as before by entry */
        for (int32_t i = jac_indptr[r]; i < jac_indptr[r + 1]; i++) {
            lat_diag[jac_indices[i]] += wts[r] * jd[i] * jd[i];
        }
    }
}

void capsheet_mf_normal_matvec(size_t n_rows, size_t n, const int32_t *indptr,
                               const int32_t *indices, const double *data, const double *w,
                               const double *x, double *tmp, double *out)
{
    for (size_t k = 0; k < n; k++) {
        out[k] = 0.0;
    }
    /* one pass: each row's product, then its share of J^T at once (out[k] still sums its
     * terms in increasing row order: the same numbers as a pass for J x and one for J^T) */
    for (size_t r = 0; r < n_rows; r++) {
        int32_t i0 = indptr[r], i1 = indptr[r + 1];
        double s = 0.0;
        for (int32_t i = i0; i < i1; i++) {
            s += data[i] * x[indices[i]];
        }
        double t = w[r] * s;
        tmp[r] = t;
        for (int32_t i = i0; i < i1; i++) {
            out[indices[i]] += data[i] * t;
        }
    }
}

static double dot(size_t n, const double *a, const double *b)
{
    double s = 0.0;
    for (size_t i = 0; i < n; i++) {
        s += a[i] * b[i];
    }
    return s;
}

/* returns x . out, summed in increasing k (as `dot` would) */
static double yaw_matvec(size_t n, size_t n_rows, size_t n_groups, const int32_t *indptr,
                       const int32_t *indices, const double *data, const double *w,
                       const double *D, const int64_t *group, const double *dg, const double *Eg,
                       double sE, double I0, const double *mw, const double *x, double *out,
                       double *tmp, double *abar, double *sig)
{
    capsheet_mf_normal_matvec(n_rows, n, indptr, indices, data, w, x, tmp, out);
    for (size_t g = 0; g < n_groups; g++) {
        abar[g] = 0.0;
    }
    for (size_t k = 0; k < n; k++) {
        abar[group[k]] += D[k] * x[k];
    }
    double ey = 0.0;
    for (size_t g = 0; g < n_groups; g++) {
        abar[g] /= dg[g];
        ey += Eg[g] * abar[g];
    }
    for (size_t g = 0; g < n_groups; g++) {
        sig[g] = (Eg[g] * abar[g] - Eg[g] * (ey / sE) + Eg[g] * (ey * I0 / (sE * sE))) / dg[g];
    }
    double xo = 0.0;
    for (size_t k = 0; k < n; k++) {
        int64_t g = group[k];
        double prior = D[k] * x[k] - D[k] * abar[g] + D[k] * sig[g];
        out[k] = out[k] + prior + mw[k] * x[k];
        xo += x[k] * out[k];
    }
    return xo;
}

/* z = inv_diag r, plus the groups' coarse correction Z (C^-1 (Z^T r)) when coarse_inv is given */
static void precondition(size_t n, size_t n_groups, const int64_t *group, const double *inv_diag,
                         const double *coarse_inv, const double *r, double *z, double *t,
                         double *c)
{
    for (size_t k = 0; k < n; k++) {
        z[k] = inv_diag[k] * r[k];
    }
    if (coarse_inv == NULL) {
        return;
    }
    for (size_t g = 0; g < n_groups; g++) {
        t[g] = 0.0;
    }
    for (size_t k = 0; k < n; k++) {
        t[group[k]] += r[k];
    }
    for (size_t g = 0; g < n_groups; g++) {
        double s = 0.0;
        for (size_t h = 0; h < n_groups; h++) {
            s += coarse_inv[n_groups * g + h] * t[h];
        }
        c[g] = s;
    }
    for (size_t k = 0; k < n; k++) {
        z[k] += c[group[k]];
    }
}

int capsheet_mf_yaw_pcg(size_t n, size_t n_rows, size_t n_groups, const int32_t *indptr,
                        const int32_t *indices, const double *data, const double *w,
                        const double *D, const int64_t *group, const double *dg,
                        const double *Eg, double sE, double I0, const double *mw,
                        const double *b, const double *inv_diag, const double *coarse_inv,
                        double rtol, int maxiter, double *x, double *work)
{
    double *tmp = work, *r = work + n_rows, *z = r + n, *p = z + n, *q = p + n;
    double *abar = q + n, *sig = abar + n_groups, *t = sig + n_groups, *c = t + n_groups;
    for (size_t k = 0; k < n; k++) {
        x[k] = 0.0;
        r[k] = b[k];
    }
    precondition(n, n_groups, group, inv_diag, coarse_inv, r, z, t, c);
    for (size_t k = 0; k < n; k++) {
        p[k] = z[k];
    }
    double rz = dot(n, r, z);
    double stop = rtol * rtol * dot(n, b, b);
    double rr = dot(n, r, r);
    int it;
    /* `pcg`'s steps with its passes over the links merged where one's sums end before the next
     * needs them; every sum runs in increasing k as before (the same numbers) */
    for (it = 0; it < maxiter; it++) {
        if (rr <= stop) {
            break;
        }
        double pq = yaw_matvec(n, n_rows, n_groups, indptr, indices, data, w, D, group, dg, Eg,
                               sE, I0, mw, p, q, tmp, abar, sig);
        double alpha = rz / pq;
        rr = 0.0;
        if (coarse_inv != NULL) {
            for (size_t g = 0; g < n_groups; g++) {
                t[g] = 0.0;
            }
        }
        for (size_t k = 0; k < n; k++) { /* the step; |r|^2 and Z^T r of the new residual */
            x[k] += alpha * p[k];
            double rk = r[k] - alpha * q[k];
            r[k] = rk;
            rr += rk * rk;
            if (coarse_inv != NULL) {
                t[group[k]] += rk;
            }
        }
        if (coarse_inv != NULL) {
            for (size_t g = 0; g < n_groups; g++) {
                double s = 0.0;
                for (size_t h = 0; h < n_groups; h++) {
                    s += coarse_inv[n_groups * g + h] * t[h];
                }
                c[g] = s;
            }
        }
        double rz_new = 0.0;
        for (size_t k = 0; k < n; k++) { /* precondition (as `precondition`) and r . z */
            double zk = inv_diag[k] * r[k];
            if (coarse_inv != NULL) {
                zk += c[group[k]];
            }
            z[k] = zk;
            rz_new += r[k] * zk;
        }
        double beta = rz_new / rz;
        for (size_t k = 0; k < n; k++) {
            p[k] = z[k] + beta * p[k];
        }
        rz = rz_new;
    }
    return it;
}

void capsheet_mf_rotate(size_t n, double *R, const double *Q)
{
    for (size_t k = 0; k < n; k++) {
        double Rn[9];
        double *Rk = R + 9 * k;
        mat3_mul(Q, Rk, Rn);
        for (int i = 0; i < 9; i++) {
            Rk[i] = Rn[i];
        }
    }
}

/* (x + pi) mod 2 pi - pi with the remainder's sign that of 2 pi, as numpy's `%` (fused.py
 * `wrap`) */
static double wrap_pi(double x)
{
    const double pi = 3.14159265358979323846;
    double y = x + pi;
    if (y >= 0.0 && y < 2.0 * pi) { /* fmod would return y itself (it is exact) */
        return y - pi;
    }
    double r = fmod(y, 2.0 * pi);
    if (r < 0.0) {
        r += 2.0 * pi;
    }
    return r - pi;
}

void capsheet_mf_mag_terms(size_t n, const double *R, const double *m, double declination,
                           double field, double dip, double field_unit, double dip_unit,
                           double *heading, double *hz, double *t_field, double *t_dip)
{
    for (size_t k = 0; k < n; k++) {
        const double *Rk = R + 9 * k;
        const double *mk = m + 3 * k;
        double W[3];
        for (int i = 0; i < 3; i++) {
            W[i] = Rk[3 * i] * mk[0] + Rk[3 * i + 1] * mk[1] + Rk[3 * i + 2] * mk[2];
        }
        double h2 = W[0] * W[0] + W[1] * W[1];
        double h = sqrt(h2); /* a field of tesla: no overflow for hypot to guard against */
        double norm = sqrt(h2 + W[2] * W[2]);
        hz[k] = h;
        heading[k] = wrap_pi(atan2(W[1], W[0]) - declination);
        t_field[k] = (norm / field - 1.0) / field_unit;
        double s = -W[2] / (norm > 1e-30 ? norm : 1e-30);
        s = s < -1.0 ? -1.0 : (s > 1.0 ? 1.0 : s);
        t_dip[k] = (asin(s) - dip) / dip_unit;
    }
}

void capsheet_mf_orientation_cov(size_t n, const double *P, const double *tilt_cov,
                                 const double *yaw_add, double *out)
{
    for (size_t k = 0; k < n; k++) {
        const double *Pk = P + 36 * k;
        double *Ck = out + 9 * k;
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) {
                Ck[3 * i + j] = Pk[6 * i + j];
            }
        }
        Ck[0] += tilt_cov[0];
        Ck[1] += tilt_cov[1];
        Ck[3] += tilt_cov[2];
        Ck[4] += tilt_cov[3];
        if (yaw_add != NULL) {
            Ck[8] += yaw_add[k];
        }
    }
}

void capsheet_mf_ddot_rates(size_t n, const double *R, const double *w, const double *wm1,
                            const double *wm2, const double *dt, int second_order, double *out)
{
    for (size_t k = 0; k < n; k++) {
        const double *a = w + 3 * k, *b = wm1 + 3 * k, *c = wm2 + 3 * k;
        double h = dt[k], wd[3];
        for (int i = 0; i < 3; i++) { /* fused.py `_relative_accel`'s differences, its order */
            wd[i] = second_order ? (3.0 * a[i] - 4.0 * b[i] + c[i]) / (2.0 * h)
                                 : (a[i] - b[i]) / h;
        }
        capsheet_mf_ddot(1, R + 9 * k, a, wd, out + 3 * k);
    }
}

void capsheet_mf_ddot(size_t n, const double *R, const double *w, const double *wdot,
                      double *out)
{
    for (size_t k = 0; k < n; k++) {
        const double *wk = w + 3 * k;
        const double *ak = wdot + 3 * k;
        const double *Rk = R + 9 * k;
        double ww = wk[0] * wk[0] + wk[1] * wk[1] + wk[2] * wk[2];
        double b[3];
        b[0] = wk[0] * wk[0] - ww;
        b[1] = wk[0] * wk[1] + ak[2];
        b[2] = wk[0] * wk[2] - ak[1];
        for (size_t i = 0; i < 3; i++) {
            out[3 * k + i] = Rk[3 * i] * b[0] + Rk[3 * i + 1] * b[1] + Rk[3 * i + 2] * b[2];
        }
    }
}

/* R <- exp([x]x) R for one link (capsheet_mf_apply's rotation) */
static void turn_link(const double *xk, double *Rk)
{
    double E[9], Rn[9];
    rodrigues(xk, E);
    mat3_mul(E, Rk, Rn);
    for (int i = 0; i < 9; i++) {
        Rk[i] = Rn[i];
    }
}

/* P <- (P + P^T) / 2 - M for one link, M symmetric given by its upper triangle (M[6 i + j],
 * j >= i): the update and the symmetrisation of capsheet_mf_apply in one pass, each entry
 * once */
static void sym_update(double *Pk, const double *M)
{
    for (int i = 0; i < 6; i++) {
        Pk[7 * i] -= M[7 * i];
        for (int j = i + 1; j < 6; j++) {
            double v = 0.5 * (Pk[6 * i + j] + Pk[6 * j + i]) - M[6 * i + j];
            Pk[6 * i + j] = v;
            Pk[6 * j + i] = v;
        }
    }
}

/* then R <- Q R (Q: 3 x 3, none when NULL) and bias <- bias + R^T (b[0], b[1], 0) with that R
 * (none when b is NULL): the sheet's common turn, as capsheet_mf_rotate and fused.py do it */
static void turn_after(double *Rk, double *bk, const double *Q, const double *b)
{
    if (Q != NULL) {
        double Rn[9];
        mat3_mul(Q, Rk, Rn);
        for (int i = 0; i < 9; i++) {
            Rk[i] = Rn[i];
        }
    }
    if (b != NULL) {
        for (int i = 0; i < 3; i++) {
            bk[i] += Rk[i] * b[0] + Rk[3 + i] * b[1];
        }
    }
}

void capsheet_mf_accel_apply(size_t n, double *R, double *bias, double *P, const double *f,
                             const double *vec, const double *r2, double gate,
                             const uint8_t *valid, double *x, double *nis, const double *turn,
                             const double *turn_bias)
{
    for (size_t k = 0; k < n; k++) {
        double *Rk = R + 9 * k, *Pk = P + 36 * k, *xk = x + 6 * k;
        double M[36];
        if (!valid[k]) {
            for (int i = 0; i < 36; i++) {
                M[i] = 0.0;
            }
            sym_update(Pk, M);
            for (int i = 0; i < 6; i++) {
                xk[i] = 0.0;
            }
            nis[k] = NAN;
            turn_after(Rk, bias + 3 * k, turn, turn_bias);
            continue;
        }
        double H[9], y[3], HP[18], Si[9], K[18];
        double m2 = capsheet_mf_accel_innovation(Rk, vec + 3 * k, f + 3 * k, Pk, r2[k], H, y, HP,
                                                 Si);
        nis[k] = m2;
        if (m2 / gate > 1.0) { /* the gate: S inflated (a division by 1 changes nothing) */
            double infl = m2 / gate;
            for (int i = 0; i < 9; i++) {
                Si[i] /= infl;
            }
        }
        for (int i = 0; i < 6; i++) { /* K = HP^T Si; x = K y */
            for (int j = 0; j < 3; j++) {
                K[3 * i + j] = HP[i] * Si[j] + HP[6 + i] * Si[3 + j] + HP[12 + i] * Si[6 + j];
            }
            xk[i] = K[3 * i] * y[0] + K[3 * i + 1] * y[1] + K[3 * i + 2] * y[2];
        }
        for (int i = 0; i < 6; i++) { /* K HP = HP^T Si HP: symmetric, its upper triangle */
            for (int j = i; j < 6; j++) {
                M[6 * i + j] = K[3 * i] * HP[j] + K[3 * i + 1] * HP[6 + j]
                               + K[3 * i + 2] * HP[12 + j];
            }
        }
        sym_update(Pk, M);
        turn_link(xk, Rk);
        for (int i = 0; i < 3; i++) {
            bias[3 * k + i] += xk[3 + i];
        }
        turn_after(Rk, bias + 3 * k, turn, turn_bias);
    }
}

void capsheet_mf_yaw_apply(size_t n, double *R, double *bias, double *P, const double *mu,
                           const double *a_diag, double *x, const double *turn,
                           const double *tilt_cov, const double *yaw_add, double *cov)
{
    for (size_t k = 0; k < n; k++) {
        double *Pk = P + 36 * k, *xk = x + 6 * k;
        double c[6], M[36];
        for (int i = 0; i < 6; i++) {
            c[i] = Pk[6 * i + 2];
        }
        double p = c[2];
        double s = (1.0 - 1.0 / (a_diag[k] * p));
        for (int i = 0; i < 6; i++) { /* g c^T s with g = c / p: symmetric, its upper triangle */
            double g = c[i] / p;
            xk[i] = g * mu[k];
            for (int j = i; j < 6; j++) {
                M[6 * i + j] = g * (c[j] * s);
            }
        }
        sym_update(Pk, M);
        turn_link(xk, R + 9 * k);
        for (int i = 0; i < 3; i++) {
            bias[3 * k + i] += xk[3 + i];
        }
        turn_after(R + 9 * k, NULL, turn, NULL);
        if (cov != NULL) { /* the output's covariance while the link's state is in cache */
            capsheet_mf_orientation_cov(1, Pk, tilt_cov, yaw_add == NULL ? NULL : yaw_add + k,
                                        cov + 9 * k);
        }
    }
}

void capsheet_mf_coarse(size_t n_rows, size_t n_groups, const int64_t *indptr,
                        const int64_t *grp, const double *val, const double *w, double *C)
{
    for (size_t i = 0; i < n_groups * n_groups; i++) {
        C[i] = 0.0;
    }
    for (size_t r = 0; r < n_rows; r++) {
        for (int64_t a = indptr[r]; a < indptr[r + 1]; a++) {
            double wa = w[r] * val[a];
            for (int64_t b = indptr[r]; b < indptr[r + 1]; b++) {
                C[(size_t)grp[a] * n_groups + (size_t)grp[b]] += wa * val[b];
            }
        }
    }
}

void capsheet_mf_jt_times(size_t n_rows, size_t n, const int32_t *indptr, const int32_t *indices,
                          const double *data, const double *v, double *out)
{
    for (size_t k = 0; k < n; k++) {
        out[k] = 0.0;
    }
    for (size_t r = 0; r < n_rows; r++) {
        for (int32_t p = indptr[r]; p < indptr[r + 1]; p++) {
            out[indices[p]] += data[p] * v[r];
        }
    }
}

void capsheet_mf_group_info(size_t nnz, size_t n_jg, size_t n_groups, size_t n,
                            const int32_t *jg_index, const double *jd, const int32_t *jg_rows,
                            const int32_t *jg_group, const double *w, const int64_t *group,
                            const double *lat_diag, double *jg, double *info, double *seen)
{
    for (size_t i = 0; i < n_jg; i++) {
        jg[i] = 0.0;
    }
    for (size_t p = 0; p < nnz; p++) {
        jg[jg_index[p]] += jd[p];
    }
    for (size_t g = 0; g < n_groups; g++) {
        info[g] = 0.0;
        seen[g] = 0.0;
    }
    for (size_t i = 0; i < n_jg; i++) {
        info[jg_group[i]] += w[jg_rows[i]] * jg[i] * jg[i];
    }
    for (size_t k = 0; k < n; k++) {
        seen[group[k]] += lat_diag[k];
    }
    for (size_t g = 0; g < n_groups; g++) {
        seen[g] = info[g] / (seen[g] > 1e-300 ? seen[g] : 1e-300);
    }
}

void capsheet_mf_mag_weights(size_t n, const double *hz, const uint8_t *ok, const double *dist,
                             const double *P, const double *count, const double *dt,
                             double noise2, double floor2, double F, double field_unit,
                             double dip_unit, double tau, double lasts, double scale2, double h,
                             double warmup, double *weight, double *mw, double *e)
{
    for (size_t k = 0; k < n; k++) {
        double m = hz[k] > 1e-30 ? hz[k] : 1e-30;
        double hz2 = m * m;
        double var0 = noise2 / hz2 + floor2;
        double c = count[k] > 1.0 ? count[k] : 1.0;
        double a = dt[k] / tau;
        double b = 1.0 / c;
        a = a > b ? a : b;
        a = a < 1e-6 ? 1e-6 : (a > 1.0 ? 1.0 : a);
        const double *Pk = P + 36 * k;
        double n2 = 2.0 * noise2 * a / (2.0 - a) + F * F * (Pk[0] + Pk[7]);
        const double *d = dist + 3 * k;
        double f1 = d[1] * field_unit, f2 = d[2] * dip_unit;
        double d2 = (f1 * f1 + f2 * f2) * F * F;
        d2 = d2 - 3.0 * n2;
        d2 = (d2 > 0.0 ? d2 : 0.0) * lasts;
        double wgt = var0 / (var0 + d2 / hz2) / (1.0 + d[0] * d[0] / scale2);
        int use = ok[k] != 0;
        weight[k] = (use && count[k] * h >= warmup) ? wgt : 0.0;
        mw[k] = use ? weight[k] / var0 : 0.0;
        if (!use) {
            e[k] = 0.0;
        }
    }
}

void capsheet_mf_dist_tests(size_t n, size_t n_groups, const int64_t *group, const uint8_t *ok,
                            const double *resid, const double *t_mag, const double *t_dip,
                            const double *dt, double tau, double heading_unit, double *dist,
                            double *resid_avg, double *count, double *sums)
{
    double *sw = sums, *swr = sums + n_groups;
    for (size_t g = 0; g < n_groups; g++) {
        sw[g] = 0.0;
        swr[g] = 0.0;
    }
    for (size_t k = 0; k < n; k++) {
        if (!ok[k]) {
            continue;
        }
        const double *d = dist + 3 * k;
        double wk = 1.0 / (1.0 + d[1] * d[1] + d[2] * d[2]);
        swr[group[k]] += wk * wrap_pi(resid[k]);
        sw[group[k]] += wk;
    }
    for (size_t k = 0; k < n; k++) {
        if (!ok[k]) {
            continue;
        }
        double rk = wrap_pi(resid[k]);
        int64_t g = group[k];
        double mean = swr[g] / (sw[g] > 1e-30 ? sw[g] : 1e-30);
        count[k] += 1.0;
        double c = count[k] > 1.0 ? count[k] : 1.0;
        double a = dt[k] / tau, b = 1.0 / c;
        a = a > b ? a : b;
        a = a < 1e-6 ? 1e-6 : (a > 1.0 ? 1.0 : a);
        double *d = dist + 3 * k;
        d[0] += a * ((rk - mean) / heading_unit - d[0]);
        d[1] += a * (t_mag[k] - d[1]);
        d[2] += a * (t_dip[k] - d[2]);
        resid_avg[k] += a * (rk - resid_avg[k]);
    }
}

double capsheet_mf_robust_mode(size_t n, const double *r, const double *w, double width,
                               double start, int iterations)
{
    double psi = start;
    for (int it = 0; it < iterations; it++) {
        double s = 0.0, sr = 0.0;
        for (size_t k = 0; k < n; k++) {
            if (!(w[k] > 0.0)) {
                continue;
            }
            double u = (r[k] - psi) / width;
            double t = 1.0 - u * u;
            if (t > 0.0) {
                double wt = w[k] * t * t;
                s += wt;
                sr += wt * r[k];
            }
        }
        if (s <= 0.0) {
            return NAN;
        }
        psi = sr / s;
    }
    return psi;
}
