/* What link_filter.c and consider_filter.c share and Python does not call (cffi reads only
 * link_filter.h). */
#ifndef CAPSHEET_LINK_INTERNAL_H
#define CAPSHEET_LINK_INTERNAL_H

/* A link's accelerometer innovation: H = R^T [v]x, y = f - R^T v, HP = H P (3 x 6), the inverse
 * Si of S = H P H^T + r2 I (symmetric, by cofactors as fused.py's `_inv_sym3`; its upper
 * triangle computed, all the cofactors read); returns y^T Si y. */
double capsheet_mf_accel_innovation(const double *Rk, const double *v, const double *fk,
                                    const double *Pk, double r2k, double *H, double *y,
                                    double *HP, double *Si);

#endif
