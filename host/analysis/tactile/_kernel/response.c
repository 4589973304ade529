/* The foam layer's response per newton to a line of uniform-pressure discs
 * (docs/tactile.md, "The contact model"; host/analysis/tactile/response.py is the reference:
 * the same formulas in numpy, which the tests compare with this file).
 *
 * A uniform disc of radius a on the layer k (w - lam^2 lap w) = p, per newton, with
 * rho = r / lam, alpha = a / lam, c = 1 / (k pi lam^2):
 *   inside  w = c (1/alpha^2 - K1(alpha) I0(rho) / alpha)
 *   outside w = c I1(alpha) K0(rho) / alpha
 * The line: nq discs at the Gauss-Legendre nodes of the segment, weighted. */
#include "response.h"

#include <math.h>
#include <stddef.h>

/* A&S 9.8.1-9.8.4: I0, I1 (t = x / 3.75) */
static double bessel_i0(double x)
{
    if (x < 3.75) {
        double t = x / 3.75;
        t *= t;
        return 1.0 + t * (3.5156229 + t * (3.0899424 + t * (1.2067492 + t * (0.2659732
               + t * (0.0360768 + t * 0.0045813)))));
    }
    double t = 3.75 / x;
    return exp(x) / sqrt(x) * (0.39894228 + t * (0.01328592 + t * (0.00225319
           + t * (-0.00157565 + t * (0.00916281 + t * (-0.02057706 + t * (0.02635537
           + t * (-0.01647633 + t * 0.00392377))))))));
}

static double bessel_i1(double x)
{
    if (x < 3.75) {
        double t = x / 3.75;
        t *= t;
        return x * (0.5 + t * (0.87890594 + t * (0.51498869 + t * (0.15084934 + t * (0.02658733
               + t * (0.00301532 + t * 0.00032411))))));
    }
    double t = 3.75 / x;
    return exp(x) / sqrt(x) * (0.39894228 + t * (-0.03988024 + t * (-0.00362018
           + t * (0.00163801 + t * (-0.01031555 + t * (0.02282967 + t * (-0.02895312
           + t * (0.01787654 + t * -0.00420059))))))));
}

/* A&S 9.8.5-9.8.8: K0, K1 (x <= 2: from I0, I1 and a series in (x/2)^2; else in 2/x) */
static double bessel_k0(double x, double i0)
{
    if (x <= 2.0) {
        double t = 0.25 * x * x;
        return -log(0.5 * x) * i0 + (-0.57721566 + t * (0.42278420 + t * (0.23069756
               + t * (0.03488590 + t * (0.00262698 + t * (0.00010750 + t * 0.00000740))))));
    }
    double t = 2.0 / x;
    return exp(-x) / sqrt(x) * (1.25331414 + t * (-0.07832358 + t * (0.02189568
           + t * (-0.01062446 + t * (0.00587872 + t * (-0.00251540 + t * 0.00053208))))));
}

static double bessel_k1(double x, double i1)
{
    if (x <= 2.0) {
        double t = 0.25 * x * x;
        return log(0.5 * x) * i1 + (1.0 + t * (0.15443144 + t * (-0.67278579 + t * (-0.18156897
               + t * (-0.01919402 + t * (-0.00110404 + t * -0.00004686)))))) / x;
    }
    double t = 2.0 / x;
    return exp(-x) / sqrt(x) * (1.25331414 + t * (0.23498619 + t * (-0.03655620
           + t * (0.01504268 + t * (-0.00780353 + t * (0.00325614 + t * -0.00068245))))));
}

void capsheet_bessel(double x, double *out)
{
    double i0 = bessel_i0(x), i1 = bessel_i1(x);
    out[0] = i0;
    out[1] = i1;
    out[2] = x > 0.0 ? bessel_k0(x, i0) : HUGE_VAL;
    out[3] = x > 0.0 ? bessel_k1(x, i1) : HUGE_VAL;
}

static int positive(double v)
{
    return isfinite(v) && v > 0.0;
}

int capsheet_line_response(int64_t n, const double *xy, double cu, double cv, double a,
                           double qx, double qy, double lam, double k, int64_t nq,
                           const double *xi, const double *wq, double *w, double *jac)
{
    if (!positive(a) || !positive(lam) || !positive(k) || n < 0 || nq < 1) {
        return -1;
    }
    const double al = a / lam;
    const double c = 1.0 / (k * M_PI * lam * lam);
    double ba[4];
    capsheet_bessel(al, ba);
    const double w_in0 = c / (al * al), w_in1 = -c * ba[3] / al;     /* + w_in1 I0(rho) */
    const double w_out = c * ba[1] / al;                               /* x K0(rho) */
    const double dr_in = -c * ba[3] / (al * lam), dr_out = -c * ba[1] / (al * lam);
    const double da_in0 = -2.0 * c / (al * al * al * lam);
    const double da_in1 = c * (al * ba[2] + 2.0 * ba[3]) / (al * al * lam);
    const double da_out = c * (al * ba[0] - 2.0 * ba[1]) / (al * al * lam);
    for (int64_t i = 0; i < n; ++i) {
        const double x = xy[2 * i], y = xy[2 * i + 1];
        double sw = 0.0, j0 = 0.0, j1 = 0.0, j2 = 0.0, j3 = 0.0, j4 = 0.0;
        for (int64_t q = 0; q < nq; ++q) {
            const double dx = x - (cu + xi[q] * qx), dy = y - (cv + xi[q] * qy);
            const double r = sqrt(dx * dx + dy * dy);
            const double rho = r / lam;
            double wv, dr, da;
            if (rho < al) {
                const double i0 = bessel_i0(rho);
                wv = w_in0 + w_in1 * i0;
                if (jac == NULL) {
                    sw += wq[q] * wv;
                    continue;
                }
                dr = dr_in * bessel_i1(rho);
                da = da_in0 + da_in1 * i0;
            } else {
                double k0, k1;
                if (rho <= 2.0) {
                    k0 = bessel_k0(rho, bessel_i0(rho));
                    k1 = jac == NULL ? 0.0 : bessel_k1(rho, bessel_i1(rho));
                } else {   /* one exponential for both */
                    const double t = 2.0 / rho, e = exp(-rho) / sqrt(rho);
                    k0 = e * (1.25331414 + t * (-0.07832358 + t * (0.02189568
                         + t * (-0.01062446 + t * (0.00587872 + t * (-0.00251540
                         + t * 0.00053208))))));
                    k1 = e * (1.25331414 + t * (0.23498619 + t * (-0.03655620
                         + t * (0.01504268 + t * (-0.00780353 + t * (0.00325614
                         + t * -0.00068245))))));
                }
                wv = w_out * k0;
                if (jac == NULL) {
                    sw += wq[q] * wv;
                    continue;
                }
                dr = dr_out * k1;
                da = da_out * k0;
            }
            sw += wq[q] * wv;
            /* G = dw/dr (dx, dy) / r: the gradient at the point, minus that at the node */
            const double g = r > 1e-300 ? dr / r : 0.0;
            const double gx = g * dx, gy = g * dy;
            j0 -= wq[q] * gx;
            j1 -= wq[q] * gy;
            j2 += wq[q] * da;
            j3 -= wq[q] * xi[q] * gx;
            j4 -= wq[q] * xi[q] * gy;
        }
        w[i] = sw;
        if (jac != NULL) {
            double *J = jac + 5 * i;
            J[0] = j0;
            J[1] = j1;
            J[2] = j2;
            J[3] = j3;
            J[4] = j4;
        }
    }
    return 0;
}
