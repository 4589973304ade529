/* The gyroscopes' fixed errors as a consider state (_consider.py): see link_filter.h. Apart
 * from link_filter.c, whose accelerometer innovation (link_internal.h) the update here shares. */
#include "link_filter.h"
#include "link_internal.h"

#include <math.h>

void capsheet_mf_consider_propagate(size_t n, size_t m, const double *R, double *P, double *C,
                                    const double *U, const double *dt, const double *s2)
{
    size_t nc = 9 * m; /* at most 2 blocks: 18 columns */
    for (size_t k = 0; k < n; k++) {
        const double *Rk = R + 9 * k, *Uk = U + 3 * m * k;
        double *Pk = P + 36 * k, *Ck = C + 6 * nc * k;
        double h = dt[k], G[9], FC[108], Y[18] = {0.0}, X[18], D[3] = {0.0, 0.0, 0.0};
        for (int i = 0; i < 9; i++) {
            G[i] = Rk[i] * h;
        }
        for (int i = 0; i < 3; i++) { /* F C: the theta rows less G times the bias rows */
            for (size_t c = 0; c < nc; c++) {
                FC[nc * i + c] = Ck[nc * i + c] - (G[3 * i] * Ck[nc * 3 + c]
                                                   + G[3 * i + 1] * Ck[nc * 4 + c]
                                                   + G[3 * i + 2] * Ck[nc * 5 + c]);
            }
        }
        for (size_t c = 3 * nc; c < 6 * nc; c++) {
            FC[c] = Ck[c];
        }
        for (size_t b = 0; b < m; b++) {
            const double *u = Uk + 3 * b;
            for (int a = 0; a < 6; a++) { /* Y = F C Omega(u)^T, summed over the blocks */
                for (int j = 0; j < 3; j++) {
                    const double *row = FC + nc * a + 9 * b + 3 * j;
                    Y[3 * a + j] += row[0] * u[0] + row[1] * u[1] + row[2] * u[2];
                }
            }
            for (int j = 0; j < 3; j++) {
                const double *v = s2 + 9 * b + 3 * j;
                D[j] += u[0] * u[0] * v[0] + u[1] * u[1] * v[1] + u[2] * u[2] * v[2];
            }
        }
        for (int a = 0; a < 6; a++) { /* X = -Y G^T */
            for (int i = 0; i < 3; i++) {
                X[3 * a + i] = -(Y[3 * a] * G[3 * i] + Y[3 * a + 1] * G[3 * i + 1]
                                 + Y[3 * a + 2] * G[3 * i + 2]);
            }
        }
        for (int a = 0; a < 6; a++) {
            for (int i = 0; i < 3; i++) {
                Pk[6 * a + i] += X[3 * a + i];
            }
        }
        for (int i = 0; i < 3; i++) {
            for (int a = 0; a < 6; a++) {
                Pk[6 * i + a] += X[3 * a + i];
            }
        }
        for (int i = 0; i < 3; i++) {
            for (int l = 0; l < 3; l++) {
                Pk[6 * i + l] += G[3 * i] * D[0] * G[3 * l] + G[3 * i + 1] * D[1] * G[3 * l + 1]
                                 + G[3 * i + 2] * D[2] * G[3 * l + 2];
            }
        }
        for (int i = 0; i < 3; i++) { /* C' = F C + Gamma Sigma */
            for (size_t b = 0; b < m; b++) {
                for (int j = 0; j < 3; j++) {
                    for (int l = 0; l < 3; l++) {
                        size_t c = 9 * b + 3 * j + l;
                        Ck[nc * i + c] = FC[nc * i + c] - G[3 * i + j] * Uk[3 * b + l] * s2[c];
                    }
                }
            }
        }
        for (size_t c = 3 * nc; c < 6 * nc; c++) {
            Ck[c] = FC[c];
        }
    }
}

void capsheet_mf_consider_accel(size_t n, size_t nc, const double *R, const double *P,
                                double *C, const double *f, const double *vec, const double *r2,
                                double gate, const uint8_t *valid)
{
    for (size_t k = 0; k < n; k++) {
        if (!valid[k]) {
            continue;
        }
        const double *Rk = R + 9 * k, *v = vec + 3 * k, *fk = f + 3 * k, *Pk = P + 36 * k;
        double *Ck = C + 6 * nc * k;
        double H[9], y[3], HP[18], Si[9], K[18], HC[54];
        double m2 = capsheet_mf_accel_innovation(Rk, v, fk, Pk, r2[k], H, y, HP, Si);
        double infl = m2 / gate > 1.0 ? m2 / gate : 1.0;
        for (int i = 0; i < 9; i++) {
            Si[i] /= infl;
        }
        for (int i = 0; i < 6; i++) {
            for (int j = 0; j < 3; j++) {
                K[3 * i + j] = HP[i] * Si[j] + HP[6 + i] * Si[3 + j] + HP[12 + i] * Si[6 + j];
            }
        }
        for (int i = 0; i < 3; i++) { /* C <- C - K H C_theta */
            for (size_t c = 0; c < nc; c++) {
                HC[nc * i + c] = H[3 * i] * Ck[c] + H[3 * i + 1] * Ck[nc + c]
                                 + H[3 * i + 2] * Ck[2 * nc + c];
            }
        }
        for (int i = 0; i < 6; i++) {
            for (size_t c = 0; c < nc; c++) {
                Ck[nc * i + c] -= K[3 * i] * HC[c] + K[3 * i + 1] * HC[nc + c]
                                  + K[3 * i + 2] * HC[2 * nc + c];
            }
        }
    }
}

void capsheet_mf_consider_yaw(size_t n, size_t nc, const double *P, double *C,
                              const double *a_diag)
{
    for (size_t k = 0; k < n; k++) {
        const double *Pk = P + 36 * k;
        double *Ck = C + 6 * nc * k;
        double p = Pk[14], row[18];
        double s = (1.0 - 1.0 / (a_diag[k] * p)) / p;
        for (size_t c = 0; c < nc; c++) {
            row[c] = Ck[2 * nc + c];
        }
        for (int i = 0; i < 6; i++) {
            double g = Pk[6 * i + 2] * s;
            for (size_t c = 0; c < nc; c++) {
                Ck[nc * i + c] -= g * row[c];
            }
        }
    }
}
