/*
 * Error-controlled quadrature of the four corner integrals of a bilinear quad (quad mean value
 * coordinates' defining integrals), float64: the same panels, orders and decisions as
 * torchcage/functional/_quad_quadrature.py (see its docstring for the error model). One pair per
 * call, depth-first over a stack of panels.
 */
#include <math.h>

#include "native.h"

#define QERR_C 50.0 /* ERROR_C */
#define QMIN_RATIO 1.3 /* MIN_RATIO */
#define QMAX_DEPTH 48 /* MAX_DEPTH */

typedef struct {
    double u0, u1, v0, v1;
    int depth;
} panel;

static inline void sheet(const double *p0, const double *b, const double *cc, const double *dd, double u, double v,
                         double *X) {
    for (int i = 0; i < 3; ++i) X[i] = p0[i] + u * b[i] + v * cc[i] + (u * v) * dd[i];
}

static inline double dist3(const double *a, const double *b) {
    double d0 = a[0] - b[0], d1 = a[1] - b[1], d2 = a[2] - b[2];
    return sqrt(d0 * d0 + d1 * d1 + d2 * d2);
}

/* Gauss order per direction for a panel at the ratio q: the least m with C m^3 rho^(-2m) <= tol
 * (0 below QMIN_RATIO, TC_QMAX_ORDER + 1 where none does), as order() in _quad_quadrature.py;
 * lc = log(QERR_C), lt = log(tol). */
static int panel_order(double q, double lc, double lt) {
    if (!(q >= QMIN_RATIO)) return 0;
    double log_rho = log(q + sqrt(q * q - 1));
    for (int k = 1; k <= TC_QMAX_ORDER; ++k)
        if (lc + 3 * log((double)k) - 2 * k * log_rho <= lt) return k;
    return TC_QMAX_ORDER + 1;
}

/* om += the four corner integrals over [u0, u1] x [v0, v1] by the m x m Gauss rule (gl: nodes and
 * weights on [0, 1] of orders 0..TC_QMAX_ORDER, (TC_QMAX_ORDER + 1, 2, TC_QMAX_ORDER)). */
static void gauss_panel(const double *p0, const double *b, const double *cc, const double *dd, const double *N0,
                        const double *Nu, const double *Nv, const panel *pn, int m, const double *gl, double *om) {
    const double *t = gl + (size_t)m * 2 * TC_QMAX_ORDER, *g = t + TC_QMAX_ORDER;
    double du = pn->u1 - pn->u0, dv = pn->v1 - pn->v0, area = du * dv;
    double s0 = 0, s1 = 0, s2 = 0, s3 = 0;
    for (int a = 0; a < m; ++a) {
        double U = pn->u0 + du * t[a];
        /* along the row: xi - x = Pu + V Qu, N = Ru + V Nv */
        double Pu[3], Qu[3], Ru[3];
        for (int i = 0; i < 3; ++i) {
            Pu[i] = p0[i] + U * b[i];
            Qu[i] = cc[i] + U * dd[i];
            Ru[i] = N0[i] + U * Nu[i];
        }
        double lo = 0, hi = 0; /* sums of f (1 - V) and f V */
        for (int l = 0; l < m; ++l) {
            double V = pn->v0 + dv * t[l];
            double X0 = Pu[0] + V * Qu[0], X1 = Pu[1] + V * Qu[1], X2 = Pu[2] + V * Qu[2];
            double r2 = X0 * X0 + X1 * X1 + X2 * X2;
            double f = ((Ru[0] + V * Nv[0]) * X0 + (Ru[1] + V * Nv[1]) * X1 + (Ru[2] + V * Nv[2]) * X2) / (r2 * r2) * g[l];
            lo += f * (1 - V);
            hi += f * V;
        }
        double ga = g[a] * area;
        s0 += (1 - U) * ga * lo;
        s1 += U * ga * lo;
        s2 += U * ga * hi;
        s3 += (1 - U) * ga * hi;
    }
    om[0] += s0;
    om[1] += s1;
    om[2] += s2;
    om[3] += s3;
}

/* Ratio |x - c_P| / R_P of a panel with corners X (relative to the point), and its centroid. */
static double panel_ratio(double X[4][3], double *ctr) {
    for (int i = 0; i < 3; ++i) ctr[i] = (X[0][i] + X[1][i] + X[2][i] + X[3][i]) * 0.25;
    double R = 0;
    for (int k = 0; k < 4; ++k) R = fmax(R, dist3(X[k], ctr));
    double d = sqrt(ctr[0] * ctr[0] + ctr[1] * ctr[1] + ctr[2] * ctr[2]);
    return R > 0 ? d / R : INFINITY;
}

int tc_quad_whole(const double *P, const int *qi, const double *x, double tol) {
    double X[4][3], ctr[3];
    for (int k = 0; k < 4; ++k)
        for (int i = 0; i < 3; ++i) X[k][i] = P[3 * qi[k] + i] - x[i];
    int m = panel_order(panel_ratio(X, ctr), log(QERR_C), log(tol));
    return m >= 1 && m <= TC_QMAX_ORDER;
}

void tc_quad_integrals(const double *p0, const double *b, const double *cc, const double *dd, const double *N0,
                       const double *Nu, const double *Nv, double us, double vs, double tol, const double *gl,
                       double *om) {
    panel stack[4 * (QMAX_DEPTH + 2)];
    int top = 0;
    const double lc = log(QERR_C), lt = log(tol);
    om[0] = om[1] = om[2] = om[3] = 0.0;
    stack[top++] = (panel){0.0, 1.0, 0.0, 1.0, 0};
    while (top > 0) {
        panel pn = stack[--top];
        if (!(pn.u1 > pn.u0) || !(pn.v1 > pn.v0)) continue; /* zero area: nothing */
        double X[4][3], ctr[3];
        sheet(p0, b, cc, dd, pn.u0, pn.v0, X[0]);
        sheet(p0, b, cc, dd, pn.u1, pn.v0, X[1]);
        sheet(p0, b, cc, dd, pn.u1, pn.v1, X[2]);
        sheet(p0, b, cc, dd, pn.u0, pn.v1, X[3]);
        int m = panel_order(panel_ratio(X, ctr), lc, lt);
        if (pn.depth == QMAX_DEPTH && (m == 0 || m > TC_QMAX_ORDER)) m = TC_QMAX_ORDER;
        if (m >= 1 && m <= TC_QMAX_ORDER) {
            gauss_panel(p0, b, cc, dd, N0, Nu, Nv, &pn, m, gl, om);
            continue;
        }
        double su, sv;
        int cut_u = 1, cut_v = 1;
        if (pn.depth == 0) {
            su = us;
            sv = vs;
        } else {
            double lu = fmax(dist3(X[0], X[1]), dist3(X[3], X[2])), lv = fmax(dist3(X[0], X[3]), dist3(X[1], X[2]));
            su = 0.5 * (pn.u0 + pn.u1);
            sv = 0.5 * (pn.v0 + pn.v1);
            cut_u = !(lv > 2 * lu);
            cut_v = !(lu > 2 * lv);
        }
        int dep = pn.depth + 1;
        double ua[2][2] = {{pn.u0, cut_u ? su : pn.u1}, {su, pn.u1}};
        double va[2][2] = {{pn.v0, cut_v ? sv : pn.v1}, {sv, pn.v1}};
        for (int hu = 0; hu <= cut_u; ++hu)
            for (int hv = 0; hv <= cut_v; ++hv)
                stack[top++] = (panel){ua[hu][0], ua[hu][1], va[hv][0], va[hv][1], dep};
    }
}
