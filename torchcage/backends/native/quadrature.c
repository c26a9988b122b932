/*
 * Error-controlled quadrature of the corner integrals of a bilinear quad, float64: the four of quad
 * mean value coordinates or the eight of quad Green coordinates, to a relative tolerance. The same
 * panels, orders and decisions as torchcage/_core/quad_quadrature.py (see its docstring for
 * the error model C m rho^(-2m)); the sheet written about the point's projection. One pair per call,
 * depth-first over a stack of panels.
 */
#include <math.h>

#include "native.h"

#define QERR_C 30.0 /* ERROR_C */
#define QMIN_RATIO 1.3 /* MIN_RATIO */
#define QMAX_DEPTH 48 /* MAX_DEPTH */
#define SPLIT_GAIN 1.5 /* SPLIT_GAIN */

typedef struct {
    double u0, u1, v0, v1;
    int depth;
} panel;

/* xi - x = h + du b + dv cc + du dv dd at offsets (du, dv) from the centre (see centred() in
 * _quad_quadrature.py). */
static inline void sheet(const double *h, const double *b, const double *cc, const double *dd, double du, double dv,
                         double *X) {
    for (int i = 0; i < 3; ++i) X[i] = h[i] + du * b[i] + dv * cc[i] + (du * dv) * dd[i];
}

static inline double dist3(const double *a, const double *b) {
    double d0 = a[0] - b[0], d1 = a[1] - b[1], d2 = a[2] - b[2];
    return sqrt(d0 * d0 + d1 * d1 + d2 * d2);
}

/* log(k) for k = 0..TC_QMAX_ORDER (entry 0 unused). */
static const double LOGK[TC_QMAX_ORDER + 1] = {
    0.0, 0.0, 0.6931471805599453, 1.0986122886681098, 1.3862943611198906, 1.6094379124341003, 1.791759469228055,
    1.9459101490553132, 2.0794415416798357, 2.1972245773362196, 2.302585092994046, 2.3978952727983707,
    2.4849066497880004, 2.5649493574615367, 2.6390573296152584, 2.70805020110221, 2.772588722239781};

/* The least m with C m rho^(-2m) <= tol at the ratio q, or TC_QMAX_ORDER + 1 where none is. */
static int least_order(double q, double lc, double lt) {
    double log_rho = log(q + sqrt(q * q - 1));
    for (int k = 1; k <= TC_QMAX_ORDER; ++k)
        if (lc + LOGK[k] - 2 * k * log_rho <= lt) return k;
    return TC_QMAX_ORDER + 1;
}

/* Gauss order per direction for a panel at the ratio q (lc = log(QERR_C), lt = log(tol)), as order()
 * in _quad_quadrature.py: 0 (split) below QMIN_RATIO, where no order up to TC_QMAX_ORDER is enough,
 * or where four children at SPLIT_GAIN times the ratio would take fewer nodes. */
static int panel_order(double q, double lc, double lt) {
    if (!(q >= QMIN_RATIO)) return 0;
    int m = least_order(q, lc, lt);
    if (m > TC_QMAX_ORDER) return 0;
    int mc = least_order(SPLIT_GAIN * q, lc, lt);
    return 4 * mc * mc < m * m ? 0 : m;
}

/* om += the four corner integrals over [u0, u1] x [v0, v1] by the m x m Gauss rule (gl: nodes and
 * weights on [0, 1] of orders 0..TC_QMAX_ORDER, (TC_QMAX_ORDER + 1, 2, TC_QMAX_ORDER)). */
static void gauss_panel(const double *p0, const double *b, const double *cc, const double *dd, const double *N0,
                        const double *Nu, const double *Nv, double us, double vs, const panel *pn, int m,
                        const double *gl, double *om) {
    const double *t = gl + (size_t)m * 2 * TC_QMAX_ORDER, *g = t + TC_QMAX_ORDER;
    double du = pn->u1 - pn->u0, dv = pn->v1 - pn->v0, area = du * dv;
    double s0 = 0, s1 = 0, s2 = 0, s3 = 0;
    for (int a = 0; a < m; ++a) {
        double U = pn->u0 + du * t[a], DU = (pn->u0 - us) + du * t[a];
        /* along the row: xi - x = Pu + DV Qu, N = Ru + DV Nv (offsets DU, DV from the centre) */
        double Pu[3], Qu[3], Ru[3];
        for (int i = 0; i < 3; ++i) {
            Pu[i] = p0[i] + DU * b[i];
            Qu[i] = cc[i] + DU * dd[i];
            Ru[i] = N0[i] + DU * Nu[i];
        }
        double lo = 0, hi = 0; /* sums of f (1 - V) and f V */
        for (int l = 0; l < m; ++l) {
            double V = pn->v0 + dv * t[l], DV = (pn->v0 - vs) + dv * t[l];
            double X0 = Pu[0] + DV * Qu[0], X1 = Pu[1] + DV * Qu[1], X2 = Pu[2] + DV * Qu[2];
            double r2 = X0 * X0 + X1 * X1 + X2 * X2;
            r2 = r2 > 0 ? r2 : INFINITY; /* a node on the point: a null set (contributes 0) */
            double f = ((Ru[0] + DV * Nv[0]) * X0 + (Ru[1] + DV * Nv[1]) * X1 + (Ru[2] + DV * Nv[2]) * X2) / (r2 * r2) * g[l];
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
    return panel_order(panel_ratio(X, ctr), log(QERR_C), log(tol)) > 0;
}

/* om += the eight corner integrals of quad Green coordinates over the panel, without the 1 / 4 pi:
 * int phi_i N.(xi - x) / |xi - x|^3 (om[0..3], the solid angle's) and int phi_i / |xi - x|
 * (om[4..7], the single layer's), as gauss_panels(green=True) in _quad_quadrature.py. */
static void gauss_panel_green(const double *p0, const double *b, const double *cc, const double *dd, const double *N0,
                              const double *Nu, const double *Nv, double us, double vs, const panel *pn, int m,
                              const double *gl, double *om) {
    const double *t = gl + (size_t)m * 2 * TC_QMAX_ORDER, *g = t + TC_QMAX_ORDER;
    double du = pn->u1 - pn->u0, dv = pn->v1 - pn->v0, area = du * dv;
    double s[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    for (int a = 0; a < m; ++a) {
        double U = pn->u0 + du * t[a], DU = (pn->u0 - us) + du * t[a];
        double Pu[3], Qu[3], Ru[3];
        for (int i = 0; i < 3; ++i) {
            Pu[i] = p0[i] + DU * b[i];
            Qu[i] = cc[i] + DU * dd[i];
            Ru[i] = N0[i] + DU * Nu[i];
        }
        double lo = 0, hi = 0, glo = 0, ghi = 0;
        for (int l = 0; l < m; ++l) {
            double V = pn->v0 + dv * t[l], DV = (pn->v0 - vs) + dv * t[l];
            double X0 = Pu[0] + DV * Qu[0], X1 = Pu[1] + DV * Qu[1], X2 = Pu[2] + DV * Qu[2];
            double r2 = X0 * X0 + X1 * X1 + X2 * X2;
            r2 = r2 > 0 ? r2 : INFINITY; /* a node on the point: a null set (contributes 0) */
            double r = sqrt(r2), ir = g[l] / r;
            double f = ((Ru[0] + DV * Nv[0]) * X0 + (Ru[1] + DV * Nv[1]) * X1 + (Ru[2] + DV * Nv[2]) * X2) / (r * r * r) * g[l];
            lo += f * (1 - V);
            hi += f * V;
            glo += ir * (1 - V);
            ghi += ir * V;
        }
        double ga = g[a] * area, w0 = (1 - U) * ga, w1 = U * ga;
        s[0] += w0 * lo;
        s[1] += w1 * lo;
        s[2] += w1 * hi;
        s[3] += w0 * hi;
        s[4] += w0 * glo;
        s[5] += w1 * glo;
        s[6] += w1 * ghi;
        s[7] += w0 * ghi;
    }
    for (int i = 0; i < 8; ++i) om[i] += s[i];
}

void tc_quad_integrals(const double *p0, const double *b, const double *cc, const double *dd, double us, double vs,
                       int on, double tol, const double *gl, int green, double *om) {
    panel stack[4 * (QMAX_DEPTH + 2)];
    int top = 0;
    const double lc = log(QERR_C), lt = log(tol);
    for (int i = 0; i < (green ? 8 : 4); ++i) om[i] = 0.0;
    /* the sheet about (us, vs), as centred() in _quad_quadrature.py */
    double h[3], b1[3], c1[3], Nc[3], Nu[3], Nv[3];
    for (int i = 0; i < 3; ++i) {
        h[i] = on ? 0.0 : p0[i] + us * b[i] + vs * cc[i] + (us * vs) * dd[i];
        b1[i] = b[i] + vs * dd[i];
        c1[i] = cc[i] + us * dd[i];
    }
    cross3(b1, c1, Nc);
    cross3(b1, dd, Nu);
    cross3(dd, c1, Nv);
    stack[top++] = (panel){0.0, 1.0, 0.0, 1.0, 0};
    while (top > 0) {
        panel pn = stack[--top];
        if (!(pn.u1 > pn.u0) || !(pn.v1 > pn.v0)) continue; /* zero area: nothing */
        double X[4][3], ctr[3];
        double a0 = pn.u0 - us, a1 = pn.u1 - us, e0 = pn.v0 - vs, e1 = pn.v1 - vs;
        sheet(h, b1, c1, dd, a0, e0, X[0]);
        sheet(h, b1, c1, dd, a1, e0, X[1]);
        sheet(h, b1, c1, dd, a1, e1, X[2]);
        sheet(h, b1, c1, dd, a0, e1, X[3]);
        int m = panel_order(panel_ratio(X, ctr), lc, lt);
        if (pn.depth == QMAX_DEPTH && m == 0) m = TC_QMAX_ORDER;
        if (m >= 1 && m <= TC_QMAX_ORDER) {
            if (green)
                gauss_panel_green(h, b1, c1, dd, Nc, Nu, Nv, us, vs, &pn, m, gl, om);
            else
                gauss_panel(h, b1, c1, dd, Nc, Nu, Nv, us, vs, &pn, m, gl, om);
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
