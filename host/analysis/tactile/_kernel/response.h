/* The foam layer's unit-force response to a line of uniform-pressure discs, with its Jacobian
 * (host/analysis/tactile/response.py's line_response; see response.c). */
#ifndef CAPSHEET_RESPONSE_H
#define CAPSHEET_RESPONSE_H

#include <stdint.h>

/* Deflection per newton w (n,) at the points xy (n, 2) of a line of nq uniform discs of
 * radius a centred at (cu, cv) + xi[q] (qx, qy), weights wq (nq,) (summing to 1), on a Vlasov
 * layer of spreading length lam and stiffness k. jac (n, 5), if not NULL, receives the
 * derivatives with respect to (cu, cv, a, qx, qy). Lengths in metres, k in Pa/m.
 * Returns 0, or -1 (nothing written) when a, lam or k is not a finite positive number. */
int capsheet_line_response(int64_t n, const double *xy, double cu, double cv, double a,
                           double qx, double qy, double lam, double k, int64_t nq,
                           const double *xi, const double *wq, double *w, double *jac);

/* The modified Bessel functions I0, I1, K0, K1 at x > 0 (Abramowitz & Stegun 9.8.1-9.8.8,
 * relative error below 3e-7), into out (4,). No failure cases (x <= 0: K0, K1 are +inf). */
void capsheet_bessel(double x, double *out);

#endif
