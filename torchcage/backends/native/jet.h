/* Second-order jets (value, gradient, Hessian) of scalar functions of the query point, for the
 * analytic derivative kernels (mvcd3d.c, mvcd2d.c). Header-only.
 *
 * A jet carries f(x), its gradient g and its Hessian H (symmetric, stored as its upper triangle).
 * The operations below are the chain and product rules, exact up to rounding; a formula written
 * with them evaluates its own first and second derivatives in closed form. In 3D the Hessian
 * order is xx, yy, zz, xy, xz, yz; in 2D xx, yy, xy.
 */
#ifndef TORCHCAGE_JET_H
#define TORCHCAGE_JET_H

#include <math.h>

typedef struct {
    double v, g[3], h[6];
} jet;

static const int JI[6] = {0, 1, 2, 0, 0, 1};
static const int JJ[6] = {0, 1, 2, 1, 2, 2};

static inline jet j_const(double c) {
    jet r = {c, {0, 0, 0}, {0, 0, 0, 0, 0, 0}};
    return r;
}

static inline jet j_add(jet a, jet b) {
    jet r;
    r.v = a.v + b.v;
    for (int k = 0; k < 3; k++) r.g[k] = a.g[k] + b.g[k];
    for (int k = 0; k < 6; k++) r.h[k] = a.h[k] + b.h[k];
    return r;
}

static inline jet j_sub(jet a, jet b) {
    jet r;
    r.v = a.v - b.v;
    for (int k = 0; k < 3; k++) r.g[k] = a.g[k] - b.g[k];
    for (int k = 0; k < 6; k++) r.h[k] = a.h[k] - b.h[k];
    return r;
}

static inline jet j_scale(jet a, double c) {
    jet r;
    r.v = a.v * c;
    for (int k = 0; k < 3; k++) r.g[k] = a.g[k] * c;
    for (int k = 0; k < 6; k++) r.h[k] = a.h[k] * c;
    return r;
}

static inline jet j_mul(jet a, jet b) {
    jet r;
    r.v = a.v * b.v;
    for (int k = 0; k < 3; k++) r.g[k] = a.v * b.g[k] + b.v * a.g[k];
    for (int k = 0; k < 6; k++)
        r.h[k] = a.v * b.h[k] + b.v * a.h[k] + a.g[JI[k]] * b.g[JJ[k]] + a.g[JJ[k]] * b.g[JI[k]];
    return r;
}

/* f(a) for a scalar function with f(a.v) = f0, f' = f1, f'' = f2. */
static inline jet j_f1(jet a, double f0, double f1, double f2) {
    jet r;
    r.v = f0;
    for (int k = 0; k < 3; k++) r.g[k] = f1 * a.g[k];
    for (int k = 0; k < 6; k++) r.h[k] = f1 * a.h[k] + f2 * a.g[JI[k]] * a.g[JJ[k]];
    return r;
}

/* f(a, b) from its value and partial derivatives up to second order. */
static inline jet j_f2(jet a, jet b, double f, double fa, double fb, double faa, double fab, double fbb) {
    jet r;
    r.v = f;
    for (int k = 0; k < 3; k++) r.g[k] = fa * a.g[k] + fb * b.g[k];
    for (int k = 0; k < 6; k++) {
        int i = JI[k], j = JJ[k];
        r.h[k] = fa * a.h[k] + fb * b.h[k] + faa * a.g[i] * a.g[j] + fab * (a.g[i] * b.g[j] + a.g[j] * b.g[i]) +
                 fbb * b.g[i] * b.g[j];
    }
    return r;
}

static inline jet j_recip(jet a) {
    double r = 1.0 / a.v;
    return j_f1(a, r, -r * r, 2.0 * r * r * r);
}

static inline jet j_div(jet a, jet b) { return j_mul(a, j_recip(b)); }

static inline jet j_sqrt(jet a) {
    double s = sqrt(a.v);
    return j_f1(a, s, 0.5 / s, -0.25 / (s * a.v));
}

static inline jet j_atan2(jet y, jet x) {
    double r2 = x.v * x.v + y.v * y.v, q = 1.0 / (r2 * r2);
    return j_f2(y, x, atan2(y.v, x.v), x.v / r2, -y.v / r2, -2.0 * x.v * y.v * q, (y.v * y.v - x.v * x.v) * q,
                2.0 * x.v * y.v * q);
}

/* atan(z)/z and its first two derivatives, by its series (|z| < 0.1, 10 terms) or closed form. */
static inline void atan_over(double z, double *f0, double *f1, double *f2) {
    if (fabs(z) < 0.1) {
        double z2 = z * z, a0 = 1.0, a1 = 0, a2 = 0, p = 1.0;  // p = z^(2k-2)
        for (int k = 1; k < 10; k++) {
            double c = ((k & 1) ? -1.0 : 1.0) / (2 * k + 1);
            a2 += c * (2 * k) * (2 * k - 1) * p;
            a1 += c * (2 * k) * p * z;
            a0 += c * p * z2;
            p *= z2;
        }
        *f0 = a0, *f1 = a1, *f2 = a2;
        return;
    }
    double A = atan(z) / z, q = 1.0 / (1.0 + z * z);
    double A1 = (q - A) / z;
    *f0 = A, *f1 = A1, *f2 = (-2.0 * z * q * q - 2.0 * A1) / z;
}

#endif
