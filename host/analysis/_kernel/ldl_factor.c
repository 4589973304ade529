/* The yaw problem's Gauss-Newton matrix factorised in the estimator's kernel: a left-looking
 * supernodal L D Lᵀ on the supernodes a first SuperLU factorisation of the same structure gave
 * (host/analysis/estimator/linalg.py, factorise). Declared in yaw_eval.h. All arrays are
 * C-contiguous, caller-owned; nothing is allocated. No -ffast-math.
 *
 * Why: on a moving sheet the chord steps' factorisation goes stale and is made again every
 * ~40 snapshots at 64x64; SuperLU's LU of the SPD matrix (both triangles, row by row checks) was
 * ~70 ms of it, a quarter of the estimator's time on such a stream. The matrix is SPD and its
 * pattern is fixed per structure, so the factor's pattern (and its supernodes) is known from the
 * first factorisation; only the values are made here.
 */
#include "yaw_eval.h"

#include <math.h>
#include <stddef.h>

/* The factorisation's loops are axpys over rows (no sums reordered): compiled for AVX2 as well
 * where the compiler and the loader can pick a clone at run time (x86-64, GCC or Clang, ELF), the
 * same arithmetic in wider lanes (no FMA: -ffp-contract=off holds for every clone). */
#if defined(__x86_64__) && defined(__GNUC__) && defined(__ELF__) && !defined(CAPSHEET_NO_CLONES)
#define FACTOR_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define FACTOR_CLONES
#endif

FACTOR_CLONES
int32_t capsheet_ldl_factor(int64_t n, const int32_t *a_ptr, const int32_t *a_idx,
                            const double *a_val, int64_t n_super, const int32_t *sn_col,
                            const int64_t *sn_row, const int32_t *rows, const int64_t *sn_diag,
                            const int64_t *sn_below, double *lval, double *diag, float *val32,
                            int64_t n_val, int32_t *iwork, double *work)
{
    int32_t *map = iwork;              /* n: a row's place in the current supernode, else -1 */
    int32_t *sup_of = map + n;         /* n: the supernode of each column */
    int32_t *head = sup_of + n;        /* n_super: first supernode J to update supernode K */
    int32_t *link = head + n_super;    /* n_super: the next in the same list */
    int32_t *next = link + n_super;    /* n_super: J's first row not yet used as a target */
    double *tmp = work;                /* largest nb of a supernode */
    int64_t s, j, k, i;
    int32_t status = 0;
    for (j = 0; j < n; ++j)
        map[j] = -1;
    for (s = 0; s < n_super; ++s) {
        head[s] = -1;
        link[s] = -1;
        next[s] = 0;
        for (j = sn_col[s]; j < sn_col[s + 1]; ++j)
            sup_of[j] = (int32_t)s;
    }
    for (s = 0; s < n_val; ++s)
        lval[s] = 0.0;
    for (s = 0; s < n_super && status == 0; ++s) {
        const int64_t k0 = sn_col[s], k1 = sn_col[s + 1], w = k1 - k0;
        const int64_t nb = sn_row[s + 1] - sn_row[s];
        const int32_t *r = rows + sn_row[s];
        double *restrict fd = lval + sn_diag[s];   /* w x w, column-major, the lower part */
        double *restrict fb = lval + sn_below[s];  /* w x nb, column-major */
        int32_t J, Jn;
        for (i = 0; i < nb; ++i)
            map[r[i]] = (int32_t)i;
        /* the matrix's own entries, on and below the diagonal */
        for (j = k0; j < k1; ++j) {
            int32_t p;
            for (p = a_ptr[j]; p < a_ptr[j + 1]; ++p) {
                const int64_t ii = a_idx[p];
                if (ii < j)
                    continue;
                if (ii < k1)
                    fd[(j - k0) * w + (ii - k0)] += a_val[p];
                else if (map[ii] >= 0)
                    fb[(j - k0) * nb + map[ii]] += a_val[p];
                else
                    status = 2;  /* an entry outside the factor's pattern */
            }
        }
        /* the updates of every earlier supernode J whose rows reach K's columns */
        for (J = head[s]; J >= 0 && status == 0; J = Jn) {
            const int64_t j0 = sn_col[J], wj = sn_col[J + 1] - j0;
            const int64_t nbj = sn_row[J + 1] - sn_row[J];
            const int32_t *rj = rows + sn_row[J];
            const double *restrict bj = lval + sn_below[J];
            const double *restrict dj = diag + j0;
            int64_t p = next[J], q = p, c;
            Jn = link[J];
            while (q < nbj && rj[q] < k1)
                ++q;
            for (i = q; i < nbj; ++i)
                if (map[rj[i]] < 0) {
                    status = 2;
                    break;
                }
            for (c = p; c < q && status == 0; ++c) {  /* K's column rj[c] */
                const int64_t kc = rj[c] - k0;
                int64_t t;
                for (i = c; i < nbj; ++i)
                    tmp[i] = 0.0;
                for (t = 0; t + 4 <= wj; t += 4) {  /* four of J's columns per pass over tmp */
                    const double *restrict c0 = bj + t * nbj, *restrict c1 = c0 + nbj;
                    const double *restrict c2 = c1 + nbj, *restrict c3 = c2 + nbj;
                    const double f0 = c0[c] * dj[t], f1 = c1[c] * dj[t + 1];
                    const double f2 = c2[c] * dj[t + 2], f3 = c3[c] * dj[t + 3];
                    for (i = c; i < nbj; ++i)
                        tmp[i] += (c0[i] * f0 + c1[i] * f1) + (c2[i] * f2 + c3[i] * f3);
                }
                for (; t < wj; ++t) {
                    const double *restrict col = bj + t * nbj;
                    const double cf = col[c] * dj[t];
                    for (i = c; i < nbj; ++i)
                        tmp[i] += col[i] * cf;
                }
                for (i = c; i < q; ++i)
                    fd[kc * w + (rj[i] - k0)] -= tmp[i];
                for (i = q; i < nbj; ++i)
                    fb[kc * nb + map[rj[i]]] -= tmp[i];
            }
            next[J] = (int32_t)q;
            if (q < nbj) {  /* J's next target: the supernode of its next row */
                const int32_t K2 = sup_of[rj[q]];
                link[J] = head[K2];
                head[K2] = J;
            }
        }
        /* K's own columns: L D Lᵀ of the diagonal block, the rows below scaled by it */
        for (k = 0; k < w && status == 0; ++k) {
            const double d = fd[k * w + k];
            double *restrict ck = fd + k * w, *restrict bk = fb + k * nb;
            int64_t jj;
            if (!(d > 0.0) || !isfinite(d)) {
                status = 1;  /* not positive definite */
                break;
            }
            diag[k0 + k] = d;
            ck[k] = 0.0;  /* the unit diagonal is implicit (the solve's layout) */
            for (i = k + 1; i < w; ++i)
                ck[i] /= d;
            for (i = 0; i < nb; ++i)
                bk[i] /= d;
            for (jj = k + 1; jj < w; ++jj) {
                const double cf = ck[jj] * d;
                double *restrict cj = fd + jj * w, *restrict bjj = fb + jj * nb;
                if (cf == 0.0)
                    continue;
                for (i = jj; i < w; ++i)
                    cj[i] -= ck[i] * cf;
                for (i = 0; i < nb; ++i)
                    bjj[i] -= bk[i] * cf;
            }
        }
        for (i = 0; i < nb; ++i)
            map[r[i]] = -1;
        if (nb > 0 && status == 0) {
            const int32_t K2 = sup_of[r[0]];
            link[s] = head[K2];
            head[K2] = (int32_t)s;
        }
    }
    if (status == 0)
        for (s = 0; s < n_val; ++s)
            val32[s] = (float)lval[s];
    return status;
}
