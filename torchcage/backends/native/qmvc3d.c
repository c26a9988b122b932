/*
 * Native CPU kernel of the quad part of torchcage's quad mean value coordinates (float64).
 *
 * The same steps and thresholds as torchcage/families/quad_mean_value/kernel.py (see its docstring): per point
 * and quad, the mean vector, the kernel kappa and least-norm solution (Cramer form plus one
 * refinement step), the two-step smooth projection, the adaptive (2n+1)^2 Riemann sum and the
 * norm-corrected lambda. The Riemann form takes QL (8) points per quad side by side (quad_pair_lanes,
 * riemann_lanes: the one-point code's operations in the same order lane by lane, so the same bits),
 * leaving rare lanes (on a corner, a flat quad's plane, near a hull face's plane) to the one-point code
 * (tc_quad_pair_c); the tolerance form one point at a time. OpenMP over points (blocks). The tests check
 * this kernel against the torch kernel.
 */
#define _GNU_SOURCE
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector atan (libmvec, max error 4 ulp) in angles4 / angles8. */
__attribute__((simd("notinbranch"))) double atan(double);
#endif

/* min and max of numbers that are not NaN (fmin and fmax are library calls). */
#define MIN2(a, b) ((a) < (b) ? (a) : (b))
#define MAX2(a, b) ((a) > (b) ? (a) : (b))

#define SPLIT_FORM_RATIO 0.01
#define REFINE 3       /* as REFINE in _qmvc3d.py */
#define NEAR_FLAT 1e-3 /* as NEAR_FLAT in _qmvc3d.py */
#define ON_QUAD_BAND 4.0 /* as ON_QUAD_BAND in _qmvc3d.py */

static const int HULL[4][3] = {{0, 1, 3}, {1, 2, 3}, {0, 2, 1}, {0, 3, 2}};

/* Quads seen from more than 10^FAR_QUAD_LO times their size blend towards, and beyond 10^FAR_QUAD_HI
 * take, the Gauss rule of the defining integrals (as FAR_QUAD_LOG and GAUSS4 in _qmvc3d.py). */
#define FAR_QUAD_LO 1.5
#define FAR_QUAD_HI 2.5
static const double GAUSS_T[4] = {0.06943184420297371, 0.33000947820757187, 0.6699905217924281, 0.9305681557970262};
static const double GAUSS_W[4] = {0.17392742256872679, 0.3260725774312732, 0.3260725774312732, 0.17392742256872679};

/* Weight of the Gauss rule: a smoothstep in log10(min_i |p_i| / size) from FAR_QUAD_LO to FAR_QUAD_HI. */
static double far_blend(const double *R, double size) {
    double rmin = MIN2(MIN2(R[0], R[1]), MIN2(R[2], R[3]));
    double ratio = rmin / size;
    /* (31.6 < 10^FAR_QUAD_LO, 316.3 > 10^FAR_QUAD_HI: the clamps below, without the log) */
    if (!(ratio > 31.6)) return 0.0;
    if (ratio > 316.3) return 1.0;
    double s = (log10(ratio) - FAR_QUAD_LO) / (FAR_QUAD_HI - FAR_QUAD_LO);
    s = s < 0 ? 0 : (s > 1 ? 1 : s);
    return s * s * (3 - 2 * s);
}

/* The four corner integrals int phi_i N.(xi - x) / |xi - x|^4 du dv by the tensor Gauss rule (as
 * gauss_weights in _qmvc3d.py): xi - x = p0 + u b + v cc + u v dd, N = N0 + u Nu + v Nv. */
static void gauss_weights(const double *p0, const double *b, const double *cc, const double *dd, const double *N0,
                          const double *Nu, const double *Nv, double *wg) {
    wg[0] = wg[1] = wg[2] = wg[3] = 0.0;
    for (int a = 0; a < 4; ++a) {
        double u = GAUSS_T[a];
        for (int l = 0; l < 4; ++l) {
            double v = GAUSS_T[l], dx[3], N[3];
            for (int c = 0; c < 3; ++c) {
                dx[c] = p0[c] + u * b[c] + v * cc[c] + u * v * dd[c];
                N[c] = N0[c] + u * Nu[c] + v * Nv[c];
            }
            double r2 = dot3(dx, dx);
            double f = dot3(N, dx) / (r2 * r2) * GAUSS_W[a] * GAUSS_W[l];
            wg[0] += (1 - u) * (1 - v) * f;
            wg[1] += u * (1 - v) * f;
            wg[2] += u * v * f;
            wg[3] += (1 - u) * v * f;
        }
    }
}

/* Angle between a and b from |a x b| (cn), a . b (d) and |a| |b| (rr), through the half-angle
 * tangent (accurate for all angles, and atan is cheaper than atan2). */
static inline double angle3(double cn, double d, double rr) {
    double t = cn / (rr + fabs(d));
    return d < 0 ? M_PI - 2 * atan(t) : 2 * atan(t);
}

/* angle3 of four (eight) lanes side by side (vector atan where libmvec serves). */
static inline void angles4(const double *cn, const double *d, const double *rr, double *out) {
#pragma omp simd
    for (int e = 0; e < 4; ++e) {
        double t = cn[e] / (rr[e] + fabs(d[e])), at = atan(t);
        out[e] = d[e] < 0 ? M_PI - 2 * at : 2 * at;
    }
}
static inline void angles8(const double *cn, const double *d, const double *rr, double *out) {
#pragma omp simd
    for (int e = 0; e < 8; ++e) {
        double t = cn[e] / (rr[e] + fabs(d[e])), at = atan(t);
        out[e] = d[e] < 0 ? M_PI - 2 * at : 2 * at;
    }
}

/* Mean vector of the quad seen from the origin of p (Eq. 16); edges through it count nothing. */
static void mean_vector(const double p[4][3], double *m) {
    double c[4][3], c2[4], cn[4], dt[4], rr[4], ang[4];
    for (int i = 0; i < 4; ++i) {
        const double *a = p[i], *b = p[(i + 1) & 3];
        cross3(a, b, c[i]);
        c2[i] = dot3(c[i], c[i]);
        cn[i] = sqrt(c2[i]);
        dt[i] = dot3(a, b);
        rr[i] = sqrt(dot3(a, a) * dot3(b, b));
    }
    angles4(cn, dt, rr, ang);
    m[0] = m[1] = m[2] = 0.0;
    for (int i = 0; i < 4; ++i) {
        if (!(c2[i] > 0)) continue;
        double g = 0.5 * ang[i] / cn[i];
        m[0] += g * c[i][0];
        m[1] += g * c[i][1];
        m[2] += g * c[i][2];
    }
}

/* Mean value weights of the triangle (a0, a1, a2) (corners minus the point): direct vector form,
 * the stable split form near its plane. */
static void triangle_weights(const double *a0, const double *a1, const double *a2, double *w) {
    const double *a[3] = {a0, a1, a2};
    double E[3][3], N[3][3], nrm[3], R[3], dots[3], Nn[3];
    for (int e = 0; e < 3; ++e) {
        const double *j = a[(e + 1) % 3], *k = a[(e + 2) % 3];
        for (int c = 0; c < 3; ++c) E[e][c] = j[c] - k[c];
        cross3(j, k, N[e]);
        Nn[e] = sqrt(dot3(N[e], N[e]));
        dots[e] = dot3(j, k);
        R[e] = sqrt(dot3(a[e], a[e]));
    }
    double cr[3], d1[3], d2[3];
    for (int c = 0; c < 3; ++c) {
        d1[c] = a1[c] - a0[c];
        d2[c] = a2[c] - a0[c];
    }
    cross3(d1, d2, cr);
    double two_area = sqrt(dot3(cr, cr));
    for (int c = 0; c < 3; ++c) nrm[c] = cr[c] / two_area;
    double h = dot3(nrm, a0);
    double rmin = fmin(R[0], fmin(R[1], R[2]));
    if (fabs(h) < SPLIT_FORM_RATIO * rmin) {
        double s[3], ell[3], gram[9];
        for (int e = 0; e < 3; ++e) {
            s[e] = dot3(N[e], nrm);
            ell[e] = sqrt(dot3(E[e], E[e]));
            for (int f = 0; f < 3; ++f) gram[3 * e + f] = dot3(E[e], E[f]);
        }
        tc_stable_face(h, s, dots, R, ell, gram, two_area, w);
        return;
    }
    double m[3] = {0.0, 0.0, 0.0};
    for (int e = 0; e < 3; ++e) {
        if (!(Nn[e] > 0)) continue;
        double g = 0.5 * angle3(Nn[e], dots[e], R[(e + 1) % 3] * R[(e + 2) % 3]) / Nn[e];
        for (int c = 0; c < 3; ++c) m[c] += g * N[e][c];
    }
    double inv = 1.0 / (two_area * h);
    for (int i = 0; i < 3; ++i) w[i] = dot3(N[i], m) * inv;
}

/* Kernel kappa of A = [p0..p3] (Eq. 26) and the rows of |kappa|^2 A^+ (Cramer form, see
 * kernel_and_pinv in _qmvc3d.py), from the six cross products c[a][b] = p_a x p_b (a < b; the
 * table holds c[b][a] = -c[a][b] too). */
static double kernel_and_pinv(const double p[4][3], double c[4][4][3], double *k, double rows[4][3]) {
    for (int a = 0; a < 4; ++a)
        for (int b = a + 1; b < 4; ++b) {
            cross3(p[a], p[b], c[a][b]);
            for (int d = 0; d < 3; ++d) c[b][a][d] = -c[a][b][d];
        }
    k[0] = dot3(p[1], c[2][3]);
    k[1] = -dot3(p[2], c[3][0]);
    k[2] = dot3(p[3], c[0][1]);
    k[3] = -dot3(p[0], c[1][2]);
    /* rows[i] = sum over j != i of (-1)^j k[j] c[y][z], (y, z) the cyclic successors of i among the
     * columns other than j (the table written out). */
    for (int d = 0; d < 3; ++d) {
        rows[0][d] = -k[1] * c[2][3][d] + k[2] * c[1][3][d] - k[3] * c[1][2][d];
        rows[1][d] = k[0] * c[2][3][d] + k[2] * c[3][0][d] - k[3] * c[2][0][d];
        rows[2][d] = k[0] * c[3][1][d] - k[1] * c[3][0][d] - k[3] * c[0][1][d];
        rows[3][d] = k[0] * c[1][2][d] - k[1] * c[0][2][d] + k[2] * c[0][1][d];
    }
    return k[0] * k[0] + k[1] * k[1] + k[2] * k[2] + k[3] * k[3];
}

static inline double badness(double r) { return (r < 0 ? -r : 0) + (r > 1 ? r - 1 : 0) + 1e-3 * fabs(r - 0.5); }

/* The root of c0 + c1 v + c2 v^2 best inside [0, 1] (the stable form of the two roots; the one
 * nearer the interval, clamped to it): intersect's and the lanes' (written once, inlined). */
static inline double unit_root(double c0, double c1, double c2) {
    double disc = c1 * c1 - 4 * c0 * c2;
    double sq = disc > 0 ? sqrt(disc) : 0.0;
    double qq = -0.5 * (c1 + (c1 >= 0 ? sq : -sq));
    double r1 = c2 != 0 ? qq / c2 : 1e300, r2 = qq != 0 ? c0 / qq : 1e300;
    double v = badness(r1) <= badness(r2) ? r1 : r2;
    return v < 0 ? 0 : (v > 1 ? 1 : v);
}

/* (u, v) where the line through the origin of p along d meets the bilinear sheet (Appendix B). */
static void intersect(const double p[4][3], const double *d, double *u_out, double *v_out) {
    double A0[3], A1[3], B0[3], B1[3], t[3], t2[3];
    for (int c = 0; c < 3; ++c) {
        A0[c] = p[0][c];
        A1[c] = p[3][c] - p[0][c];
        B0[c] = p[1][c];
        B1[c] = p[2][c] - p[1][c];
    }
    cross3(A0, B0, t);
    double c0 = dot3(t, d);
    cross3(A0, B1, t);
    cross3(A1, B0, t2);
    double c1 = dot3(t, d) + dot3(t2, d);
    cross3(A1, B1, t);
    double c2 = dot3(t, d);
    double v = unit_root(c0, c1, c2);
    double a[3], e[3];
    for (int c = 0; c < 3; ++c) {
        a[c] = A0[c] + v * A1[c];
        e[c] = B0[c] + v * B1[c] - a[c];
    }
    double d2 = dot3(d, d), inv = d2 > 0 ? 1.0 / d2 : 0.0;
    double ed = dot3(e, d) * inv, ad = dot3(a, d) * inv, ep[3], ap[3];
    for (int c = 0; c < 3; ++c) {
        ep[c] = e[c] - ed * d[c];
        ap[c] = a[c] - ad * d[c];
    }
    double ee = dot3(ep, ep);
    double u = ee > 0 ? -dot3(ap, ep) / ee : 0.5;
    *u_out = u < 0 ? 0 : (u > 1 ? 1 : u);
    *v_out = v;
}

/* sk[k] = k / n (k < 2 n + 1), from the caller. */
static void grid(double t, int n, const double *sk, double *nodes, double *len) {
    int K = 2 * n + 1;
    for (int k = 0; k < K; ++k) {
        double s = sk[k];
        nodes[k] = s <= 1 ? s * t : t + (s - 1) * (1 - t);
    }
    for (int k = 0; k < K; ++k) len[k] = (nodes[k + 1 < K ? k + 1 : K - 1] - nodes[k > 0 ? k - 1 : 0]) / 2;
}

/* The Riemann estimate Omega (Eqs. 22-23) of the four corner integrals on the adaptive grid around
 * (u, v), separable in the bilinear basis (as riemann_sums in _qmvc3d.py); un: 4 KP scratch (KP: 2 n + 1
 * rounded up to a multiple of 4), sk: k / n. The rows' samples go four at a time: the lanes past
 * 2 n + 1 repeat the last node with weight zero. */
static void riemann_sums(const double *p0, const double *b, const double *cc, const double *dd, const double *N0,
                         const double *Nu, const double *Nv, double u, double v, int n, const double *sk, double *un,
                         double *om) {
    const int K = 2 * n + 1, KP = (K + 3) & ~3;
    double *ua = un + KP, *vn = ua + KP, *va = vn + KP;
    grid(u, n, sk, un, ua);
    grid(v, n, sk, vn, va);
    for (int l = K; l < KP; ++l) {
        vn[l] = vn[K - 1];
        va[l] = 0.0;
    }
    double S = 0, Su = 0, Sv = 0, Suv = 0;
    for (int a = 0; a < K; ++a) {
        double Pu[3], Qu[3], Ru[3];
        for (int c = 0; c < 3; ++c) {
            Pu[c] = p0[c] + un[a] * b[c];
            Qu[c] = cc[c] + un[a] * dd[c];
            Ru[c] = N0[c] + un[a] * Nu[c];
        }
        double s0[4] = {0, 0, 0, 0}, s1[4] = {0, 0, 0, 0};
        for (int l0 = 0; l0 < KP; l0 += 4) {
#pragma omp simd
            for (int j = 0; j < 4; ++j) {
                double vv = vn[l0 + j];
                double d0 = Pu[0] + vv * Qu[0], d1 = Pu[1] + vv * Qu[1], d2 = Pu[2] + vv * Qu[2];
                double r2 = d0 * d0 + d1 * d1 + d2 * d2;
                double Nd = (Ru[0] + vv * Nv[0]) * d0 + (Ru[1] + vv * Nv[1]) * d1 + (Ru[2] + vv * Nv[2]) * d2;
                double f = Nd * va[l0 + j] / (r2 * r2);
                s0[j] += f;
                s1[j] += f * vv;
            }
        }
        double acc0 = ((s0[0] + s0[1]) + (s0[2] + s0[3])) * ua[a], acc1 = ((s1[0] + s1[1]) + (s1[2] + s1[3])) * ua[a];
        S += acc0;
        Sv += acc1;
        Su += un[a] * acc0;
        Suv += un[a] * acc1;
    }
    om[0] = S - Su - Sv + Suv;
    om[1] = Su - Suv;
    om[2] = Suv;
    om[3] = Sv - Suv;
}

/* Per point-quad quantities shared by QMVC and QGC: the corners minus the point, the kernel
 * kappa and pseudo-inverse rows, the mean vector, the tetrahedron's edge terms, the sheet's
 * parametrisation, and the smooth projection (u, v) of Algorithm 1 (see project in _qmvc3d.py).
 * Without project, (u, v) is the centre (or the corner the point sits on) and on means on a corner:
 * for pairs whose quadrature never splits the quad, which are far from it. */
void tc_quad_const(const double *P, const int *qi, quad_const *qc) {
    /* (from the corners, not from p: differences of p lose eps |x - q| / size far away) */
    const double *q0 = P + 3 * qi[0], *q1 = P + 3 * qi[1], *q2 = P + 3 * qi[2], *q3 = P + 3 * qi[3];
    for (int c = 0; c < 3; ++c) {
        qc->b[c] = q1[c] - q0[c];
        qc->cc[c] = q3[c] - q0[c];
        qc->dd[c] = q0[c] - q1[c] + q2[c] - q3[c];
    }
    cross3(qc->b, qc->cc, qc->N0);
    cross3(qc->b, qc->dd, qc->Nu);
    cross3(qc->dd, qc->cc, qc->Nv);
    for (int c = 0; c < 3; ++c) qc->nq[c] = qc->N0[c] + 0.5 * (qc->Nu[c] + qc->Nv[c]);
    double area2 = 0.0;
    for (int i = 0; i < 4; ++i) {
        const double *a1 = P + 3 * qi[(i + 1) & 3], *a2 = P + 3 * qi[(i + 2) & 3], *a3 = P + 3 * qi[(i + 3) & 3];
        double e1[3] = {a2[0] - a1[0], a2[1] - a1[1], a2[2] - a1[2]}, e2[3] = {a3[0] - a1[0], a3[1] - a1[1], a3[2] - a1[2]};
        double cr[3];
        cross3(e1, e2, cr);
        area2 += sqrt(dot3(cr, cr));
    }
    qc->area2 = area2;
    /* Twice the hull faces' areas (from the corners: the point-relative corners gave the same at
     * rounding level). */
    for (int f = 0; f < 4; ++f) {
        const double *a0 = P + 3 * qi[HULL[f][0]], *a1 = P + 3 * qi[HULL[f][1]], *a2 = P + 3 * qi[HULL[f][2]];
        double e1[3] = {a1[0] - a0[0], a1[1] - a0[1], a1[2] - a0[2]}, e2[3] = {a2[0] - a0[0], a2[1] - a0[1], a2[2] - a0[2]};
        double cr[3];
        cross3(e1, e2, cr);
        qc->hull_two_area[f] = sqrt(dot3(cr, cr));
    }
}

void tc_quad_pair_c(const double *P, const int *qi, const quad_const *qc, const double *x, double tol, int project,
                    quad_pair *qp) {
    double p[4][3], R2[4];
    int vertex = -1;
    for (int i = 0; i < 4; ++i) {
        for (int c = 0; c < 3; ++c) p[i][c] = P[3 * qi[i] + c] - x[c];
        R2[i] = dot3(p[i], p[i]);
        if (R2[i] <= tol * tol && (vertex < 0 || R2[i] < R2[vertex])) vertex = i;
    }
    double m[3], k[4], rows[4][3], c[4][4][3], g[4][4], R[4];
    double D = kernel_and_pinv(p, c, k, rows);
    /* Edge terms theta_ab / (2 |p_a x p_b|) of the tetrahedron's six edges, shared by the
     * quad's mean vector (its four boundary edges) and the hull faces' weights. */
    for (int i = 0; i < 4; ++i) R[i] = sqrt(R2[i]);
    {
        /* (the six angles side by side: one or two vector atan calls; lanes 6, 7 unused) */
        static const int EA[8] = {0, 1, 2, 0, 0, 1, 0, 0}, EB[8] = {1, 2, 3, 3, 2, 3, 1, 1};
        double c2[8], cn[8], dt[8], rr[8], ang[8];
        for (int e = 0; e < 6; ++e) {
            const int a = EA[e], bb = EB[e];
            c2[e] = dot3(c[a][bb], c[a][bb]);
            cn[e] = sqrt(c2[e]);
            dt[e] = dot3(p[a], p[bb]);
            rr[e] = R[a] * R[bb];
        }
        for (int e = 6; e < 8; ++e) {
            c2[e] = cn[e] = 0.0;
            dt[e] = rr[e] = 1.0;
        }
        angles8(cn, dt, rr, ang);
        for (int e = 0; e < 6; ++e) {
            const int a = EA[e], bb = EB[e];
            /* (without project, a diagonal (e = 4, 5) serves the hull faces alone: none) */
            g[a][bb] = g[bb][a] = (e >= 4 && !project) ? 0.0 : (c2[e] > 0 ? 0.5 * ang[e] / cn[e] : 0.0);
        }
    }
    for (int d = 0; d < 3; ++d) m[d] = 0.0;
    for (int i = 0; i < 4; ++i) {
        int j = (i + 1) & 3;
        for (int d = 0; d < 3; ++d) m[d] += g[i][j] * c[i][j][d];
    }
    double kabs = fabs(k[0]) + fabs(k[1]) + fabs(k[2]) + fabs(k[3]);
    /* kappa vanishes only for a planar quad and a point on its plane: |kappa|_1 = |h| sum_i 2 A_i
     * there (A_i the corner triangles' areas), so the test below is |h| <= tol (as in _qmvc3d.py). */
    int flat = kabs <= tol * qc->area2;
    double alpha = k[0] + k[1] + k[2] + k[3], sgn = alpha >= 0 ? 1.0 : -1.0;
    int inside = alpha != 0;
    for (int i = 0; i < 4; ++i) inside = inside && (k[i] * sgn >= -1e-13 * kabs);
    /* The signs of kappa mean nothing when it is at the level of its rounding error (a point on
     * the plane of a nearly planar quad, off it): not inside then (as in _qmvc3d.py). */
    double noise = 16.0 * DBL_EPSILON * (R[1] * R[2] * R[3] + R[0] * R[2] * R[3] + R[0] * R[1] * R[3] + R[0] * R[1] * R[2]);
    inside = inside && kabs > noise;
    const double *b = qc->b, *cc = qc->cc, *dd = qc->dd;
    /* Projection (Algorithm 1). */
    double pp[4][3], d[3], u = 0.5, v = 0.5;
    memcpy(pp, p, sizeof(pp));
    if (!project) {
        /* the centre, or the corner below */
    } else if (flat) {
        memcpy(d, qc->nq, sizeof(d));
    } else if (inside || vertex >= 0) {
        memcpy(d, m, sizeof(d));
    } else {
        double num[3] = {0, 0, 0}, den = 0;
        for (int f = 0; f < 4; ++f) {
            const int *h = HULL[f];
            double wt[3];
            /* The face's determinant is +-kappa of the corner it leaves out. */
            double det = dot3(p[h[0]], c[h[1]][h[2]]);
            double two_area = qc->hull_two_area[f];
            double rmin = MIN2(R[h[0]], MIN2(R[h[1]], R[h[2]]));
            if (fabs(det) < SPLIT_FORM_RATIO * rmin * two_area) {
                triangle_weights(p[h[0]], p[h[1]], p[h[2]], wt); /* stable form near the plane */
            } else {
                double mt[3] = {0, 0, 0};
                for (int e = 0; e < 3; ++e) {
                    int j = h[(e + 1) % 3], l = h[(e + 2) % 3];
                    for (int d = 0; d < 3; ++d) mt[d] += g[j][l] * c[j][l][d];
                }
                for (int i = 0; i < 3; ++i) wt[i] = dot3(c[h[(i + 1) % 3]][h[(i + 2) % 3]], mt) / det;
            }
            for (int i = 0; i < 3; ++i) {
                double a = fabs(wt[i]);
                if (!isfinite(a)) a = 0.0;
                den += a;
                for (int d = 0; d < 3; ++d) num[d] += a * P[3 * qi[h[i]] + d];
            }
        }
        if (den > 0)
            for (int i = 0; i < 4; ++i)
                for (int c = 0; c < 3; ++c) pp[i][c] = P[3 * qi[i] + c] - num[c] / den;
        mean_vector(pp, d);
    }
    if (vertex >= 0) { /* on a corner: its parameters */
        u = (vertex == 1 || vertex == 2) ? 1.0 : 0.0;
        v = vertex >= 2 ? 1.0 : 0.0;
    } else if (project) {
        intersect(pp, d, &u, &v);
    }
    double xi[3];
    for (int c = 0; c < 3; ++c) xi[c] = p[0][c] + u * b[c] + v * cc[c] + u * v * dd[c];
    memcpy(qp->p, p, sizeof(p));
    memcpy(qp->R, R, sizeof(R));
    memcpy(qp->m, m, sizeof(m));
    memcpy(qp->k, k, sizeof(k));
    memcpy(qp->rows, rows, sizeof(rows));
    memcpy(qp->b, b, sizeof(qp->b));
    memcpy(qp->cc, cc, sizeof(qp->cc));
    memcpy(qp->dd, dd, sizeof(qp->dd));
    qp->D = D;
    qp->kabs = kabs;
    qp->flat = flat;
    qp->inside = inside;
    qp->u = u;
    qp->v = v;
    qp->vertex = vertex;
    /* (A point within tol of a planar quad's plane gets no weight from it off the quad: within tol of
     * its boundary too, it is on the quad, or it would get no weight from either face of an edge.) */
    /* (ON_QUAD_BAND tolerances: the projection is not the nearest point of a curved sheet; as in
     * _qmvc3d.py) */
    qp->on = vertex >= 0 || (project && dot3(xi, xi) <= (flat ? 2.0 : ON_QUAD_BAND * ON_QUAD_BAND) * tol * tol);
}

/* QL points for one quad side by side (the Riemann form: project on): tc_quad_pair_c's steps, the
 * same operations in the same order lane by lane (so the same bits, the vector atan included), each
 * step a loop over the lanes. The lanes on a corner, on a flat quad's plane, or outside the
 * tetrahedron with a hull face near its plane (the split form) are left to tc_quad_pair_c (redo). */
#define LANES _Pragma("omp simd") for (int j = 0; j < QL; ++j) /* (QL, quad_lanes: native.h) */

/* (inlined in tc_qmvc3d as before QGC's entry below gave it a second caller: the same code there) */
#if defined(__GNUC__) || defined(__clang__)
__attribute__((always_inline))
#endif
static inline void quad_pair_lanes(const double *P, const int *qi, const quad_const *qc, const double *X, int nl,
                                   double tol, quad_lanes *L) {
    const double *q[4] = {P + 3 * qi[0], P + 3 * qi[1], P + 3 * qi[2], P + 3 * qi[3]};
    const double *b = qc->b, *cc = qc->cc, *dd = qc->dd;
    const double area2 = qc->area2, tol2 = tol * tol;
    double xs[3][QL], R2[4][QL], C[4][4][3][QL], G[4][4][QL], T[6][QL], AT[6][QL], C2[6][QL], CN[6][QL], DT[6][QL];
    double (*p)[3][QL] = L->p, (*R)[QL] = L->R, (*k)[QL] = L->k;
    int vert[QL], flat[QL], split[QL];
    for (int j = 0; j < QL; ++j)
        for (int c = 0; c < 3; ++c) xs[c][j] = X[3 * (j < nl ? j : 0) + c];
    for (int i = 0; i < 4; ++i)
        for (int c = 0; c < 3; ++c) {
            const double qic = q[i][c];
            LANES p[i][c][j] = qic - xs[c][j];
        }
    for (int i = 0; i < 4; ++i) {
        LANES {
            R2[i][j] = p[i][0][j] * p[i][0][j] + p[i][1][j] * p[i][1][j] + p[i][2][j] * p[i][2][j];
            R[i][j] = sqrt(R2[i][j]);
        }
    }
    LANES vert[j] = (R2[0][j] <= tol2) | (R2[1][j] <= tol2) | (R2[2][j] <= tol2) | (R2[3][j] <= tol2);
    /* c[a][b] = p_a x p_b, kappa, |kappa|^2 A^+ rows (kernel_and_pinv) */
    static const int EA[6] = {0, 1, 2, 0, 0, 1}, EB[6] = {1, 2, 3, 3, 2, 3};
    for (int e = 0; e < 6; ++e) {
        const int a = EA[e], bb = EB[e];
        LANES {
            double c0 = p[a][1][j] * p[bb][2][j] - p[a][2][j] * p[bb][1][j];
            double c1 = p[a][2][j] * p[bb][0][j] - p[a][0][j] * p[bb][2][j];
            double c2 = p[a][0][j] * p[bb][1][j] - p[a][1][j] * p[bb][0][j];
            C[a][bb][0][j] = c0, C[a][bb][1][j] = c1, C[a][bb][2][j] = c2;
            C[bb][a][0][j] = -c0, C[bb][a][1][j] = -c1, C[bb][a][2][j] = -c2;
        }
    }
#define LDOT(A, B) (A[0][j] * B[0][j] + A[1][j] * B[1][j] + A[2][j] * B[2][j])
    LANES {
        k[0][j] = LDOT(p[1], C[2][3]);
        k[1][j] = -LDOT(p[2], C[3][0]);
        k[2][j] = LDOT(p[3], C[0][1]);
        k[3][j] = -LDOT(p[0], C[1][2]);
    }
    for (int d = 0; d < 3; ++d) {
        LANES {
            L->rows[0][d][j] = -k[1][j] * C[2][3][d][j] + k[2][j] * C[1][3][d][j] - k[3][j] * C[1][2][d][j];
            L->rows[1][d][j] = k[0][j] * C[2][3][d][j] + k[2][j] * C[3][0][d][j] - k[3][j] * C[2][0][d][j];
            L->rows[2][d][j] = k[0][j] * C[3][1][d][j] - k[1][j] * C[3][0][d][j] - k[3][j] * C[0][1][d][j];
            L->rows[3][d][j] = k[0][j] * C[1][2][d][j] - k[1][j] * C[0][2][d][j] + k[2][j] * C[0][1][d][j];
        }
    }
    LANES L->D[j] = k[0][j] * k[0][j] + k[1][j] * k[1][j] + k[2][j] * k[2][j] + k[3][j] * k[3][j];
    /* the six edge terms g (theta / (2 |p_a x p_b|)) */
    for (int e = 0; e < 6; ++e) {
        const int a = EA[e], bb = EB[e];
        LANES {
            double c2 = LDOT(C[a][bb], C[a][bb]), cn = sqrt(c2), dt = LDOT(p[a], p[bb]), rr = R[a][j] * R[bb][j];
            C2[e][j] = c2, CN[e][j] = cn, DT[e][j] = dt;
            T[e][j] = cn / (rr + fabs(dt));
        }
    }
    for (int e = 0; e < 6; ++e) LANES AT[e][j] = atan(T[e][j]);
    for (int e = 0; e < 6; ++e) {
        const int a = EA[e], bb = EB[e];
        LANES {
            double ang = DT[e][j] < 0 ? M_PI - 2 * AT[e][j] : 2 * AT[e][j];
            double g = C2[e][j] > 0 ? 0.5 * ang / CN[e][j] : 0.0;
            G[a][bb][j] = g, G[bb][a][j] = g;
        }
    }
    for (int d = 0; d < 3; ++d) {
        LANES {
            double s = 0.0;
            s += G[0][1][j] * C[0][1][d][j];
            s += G[1][2][j] * C[1][2][d][j];
            s += G[2][3][j] * C[2][3][d][j];
            s += G[3][0][j] * C[3][0][d][j];
            L->m[d][j] = s;
        }
    }
    LANES {
        double k0 = k[0][j], k1 = k[1][j], k2 = k[2][j], k3 = k[3][j];
        double kabs = fabs(k0) + fabs(k1) + fabs(k2) + fabs(k3);
        flat[j] = kabs <= tol * area2;
        double alpha = k0 + k1 + k2 + k3, sgn = alpha >= 0 ? 1.0 : -1.0;
        double lim = -1e-13 * kabs;
        int inside = (alpha != 0) & (k0 * sgn >= lim) & (k1 * sgn >= lim) & (k2 * sgn >= lim) & (k3 * sgn >= lim);
        double r0 = R[0][j], r1 = R[1][j], r2 = R[2][j], r3 = R[3][j];
        double noise = 16.0 * DBL_EPSILON * (r1 * r2 * r3 + r0 * r2 * r3 + r0 * r1 * r3 + r0 * r1 * r2);
        L->inside[j] = inside & (kabs > noise);
        L->kabs[j] = kabs;
        split[j] = 0;
    }
    /* The hull faces' weights (outside lanes): the projection's centre num / den. */
    double num[3][QL], den[QL], PP[4][3][QL], DIR[3][QL];
    LANES num[0][j] = num[1][j] = num[2][j] = den[j] = 0.0;
    for (int f = 0; f < 4; ++f) {
        const int h0 = HULL[f][0], h1 = HULL[f][1], h2 = HULL[f][2];
        const double ta = qc->hull_two_area[f];
        const double *q0 = q[h0], *q1 = q[h1], *q2 = q[h2];
        LANES {
            double det = LDOT(p[h0], C[h1][h2]);
            double rmin = MIN2(R[h0][j], MIN2(R[h1][j], R[h2][j]));
            split[j] |= fabs(det) < SPLIT_FORM_RATIO * rmin * ta;
            double g12 = G[h1][h2][j], g20 = G[h2][h0][j], g01 = G[h0][h1][j], mt[3];
#define MT(d) (((0.0 + g12 * C[h1][h2][d][j]) + g20 * C[h2][h0][d][j]) + g01 * C[h0][h1][d][j])
            mt[0] = MT(0);
            mt[1] = MT(1);
            mt[2] = MT(2);
#undef MT
            double w0 = (C[h1][h2][0][j] * mt[0] + C[h1][h2][1][j] * mt[1] + C[h1][h2][2][j] * mt[2]) / det;
            double w1 = (C[h2][h0][0][j] * mt[0] + C[h2][h0][1][j] * mt[1] + C[h2][h0][2][j] * mt[2]) / det;
            double w2 = (C[h0][h1][0][j] * mt[0] + C[h0][h1][1][j] * mt[1] + C[h0][h1][2][j] * mt[2]) / det;
            double a0 = fabs(w0), a1 = fabs(w1), a2 = fabs(w2);
            a0 = a0 <= DBL_MAX ? a0 : 0.0; /* (not finite: none) */
            a1 = a1 <= DBL_MAX ? a1 : 0.0;
            a2 = a2 <= DBL_MAX ? a2 : 0.0;
            double dn = den[j], n0 = num[0][j], n1 = num[1][j], n2 = num[2][j];
            dn += a0, n0 += a0 * q0[0], n1 += a0 * q0[1], n2 += a0 * q0[2];
            dn += a1, n0 += a1 * q1[0], n1 += a1 * q1[1], n2 += a1 * q1[2];
            dn += a2, n0 += a2 * q2[0], n1 += a2 * q2[1], n2 += a2 * q2[2];
            den[j] = dn, num[0][j] = n0, num[1][j] = n1, num[2][j] = n2;
        }
    }
    for (int i = 0; i < 4; ++i)
        for (int c = 0; c < 3; ++c) {
            const double qic = q[i][c];
            LANES PP[i][c][j] = den[j] > 0 ? qic - num[c][j] / den[j] : p[i][c][j];
        }
    /* their mean vector (mean_vector) */
    double CV[4][3][QL], T4[4][QL], AT4[4][QL], C24[4][QL], CN4[4][QL], DT4[4][QL];
    for (int i = 0; i < 4; ++i) {
        const int i1 = (i + 1) & 3;
        LANES {
            double c0 = PP[i][1][j] * PP[i1][2][j] - PP[i][2][j] * PP[i1][1][j];
            double c1 = PP[i][2][j] * PP[i1][0][j] - PP[i][0][j] * PP[i1][2][j];
            double c2v = PP[i][0][j] * PP[i1][1][j] - PP[i][1][j] * PP[i1][0][j];
            CV[i][0][j] = c0, CV[i][1][j] = c1, CV[i][2][j] = c2v;
            double c2 = c0 * c0 + c1 * c1 + c2v * c2v, cn = sqrt(c2), dt = LDOT(PP[i], PP[i1]);
            double rr = sqrt(LDOT(PP[i], PP[i]) * LDOT(PP[i1], PP[i1]));
            C24[i][j] = c2, CN4[i][j] = cn, DT4[i][j] = dt;
            T4[i][j] = cn / (rr + fabs(dt));
        }
    }
    for (int i = 0; i < 4; ++i) LANES AT4[i][j] = atan(T4[i][j]);
    for (int i = 0; i < 4; ++i) {
        LANES {
            double ang = DT4[i][j] < 0 ? M_PI - 2 * AT4[i][j] : 2 * AT4[i][j];
            T4[i][j] = C24[i][j] > 0 ? 0.5 * ang / CN4[i][j] : 0.0; /* (g) */
        }
    }
    for (int d = 0; d < 3; ++d) {
        LANES {
            double s = 0.0;
            s += C24[0][j] > 0 ? T4[0][j] * CV[0][d][j] : 0.0;
            s += C24[1][j] > 0 ? T4[1][j] * CV[1][d][j] : 0.0;
            s += C24[2][j] > 0 ? T4[2][j] * CV[2][d][j] : 0.0;
            s += C24[3][j] > 0 ? T4[3][j] * CV[3][d][j] : 0.0;
            DIR[d][j] = L->inside[j] ? L->m[d][j] : s;
        }
    }
    for (int i = 0; i < 4; ++i)
        for (int c = 0; c < 3; ++c) LANES PP[i][c][j] = L->inside[j] ? p[i][c][j] : PP[i][c][j];
    /* (u, v) where the line along DIR meets the sheet (intersect), and the on-quad test */
    LANES {
        const double A00 = PP[0][0][j], A01 = PP[0][1][j], A02 = PP[0][2][j];
        const double A10 = PP[3][0][j] - PP[0][0][j], A11 = PP[3][1][j] - PP[0][1][j], A12 = PP[3][2][j] - PP[0][2][j];
        const double B00 = PP[1][0][j], B01 = PP[1][1][j], B02 = PP[1][2][j];
        const double B10 = PP[2][0][j] - PP[1][0][j], B11 = PP[2][1][j] - PP[1][1][j], B12 = PP[2][2][j] - PP[1][2][j];
        const double d0 = DIR[0][j], d1 = DIR[1][j], d2v = DIR[2][j];
        /* (cross3 and dot3 written out: the vectoriser takes no small arrays here) */
#define CRD(ax, ay, az, bx, by, bz) \
    ((ay * bz - az * by) * d0 + (az * bx - ax * bz) * d1 + (ax * by - ay * bx) * d2v)
        double c0 = CRD(A00, A01, A02, B00, B01, B02);
        double c1 = CRD(A00, A01, A02, B10, B11, B12) + CRD(A10, A11, A12, B00, B01, B02);
        double c2 = CRD(A10, A11, A12, B10, B11, B12);
#undef CRD
        double v = unit_root(c0, c1, c2);
        double a0 = A00 + v * A10, a1 = A01 + v * A11, a2 = A02 + v * A12;
        double e0 = B00 + v * B10 - a0, e1 = B01 + v * B11 - a1, e2 = B02 + v * B12 - a2;
        double dd2 = d0 * d0 + d1 * d1 + d2v * d2v, inv = dd2 > 0 ? 1.0 / dd2 : 0.0;
        double ed = (e0 * d0 + e1 * d1 + e2 * d2v) * inv, ad = (a0 * d0 + a1 * d1 + a2 * d2v) * inv;
        double ep0 = e0 - ed * d0, ep1 = e1 - ed * d1, ep2 = e2 - ed * d2v;
        double ap0 = a0 - ad * d0, ap1 = a1 - ad * d1, ap2 = a2 - ad * d2v;
        double ee = ep0 * ep0 + ep1 * ep1 + ep2 * ep2;
        double u = ee > 0 ? -(ap0 * ep0 + ap1 * ep1 + ap2 * ep2) / ee : 0.5;
        u = u < 0 ? 0 : (u > 1 ? 1 : u);
        double xi0 = p[0][0][j] + u * b[0] + v * cc[0] + u * v * dd[0];
        double xi1 = p[0][1][j] + u * b[1] + v * cc[1] + u * v * dd[1];
        double xi2 = p[0][2][j] + u * b[2] + v * cc[2] + u * v * dd[2];
        L->u[j] = u;
        L->v[j] = v;
        L->on[j] = xi0 * xi0 + xi1 * xi1 + xi2 * xi2 <= ON_QUAD_BAND * ON_QUAD_BAND * tol * tol;
        L->redo[j] = vert[j] | flat[j] | (split[j] & !L->inside[j]);
    }
#undef LDOT
}

/* (QGC's entry: quad_pair_lanes stays static, so tc_qmvc3d's calls compile as before) */
void tc_quad_pair_lanes(const double *P, const int *qi, const quad_const *qc, const double *X, int nl, double tol,
                        quad_lanes *L) {
    quad_pair_lanes(P, qi, qc, X, nl, tol, L);
}

/* riemann_sums for the QL lanes of quad_pair_lanes (their p0, u, v) side by side, the same sums in the
 * same order lane by lane (the zero-weight lanes of riemann_sums add nothing). ln: 4 (2 n + 1) QL
 * scratch; om: (4, QL). */
static void riemann_lanes(const quad_const *qc, const quad_lanes *L, int n, const double *sk, double *ln,
                          double om[4][QL]) {
    const int K = 2 * n + 1;
    double(*un)[QL] = (double(*)[QL])ln, (*ua)[QL] = un + K, (*vn)[QL] = ua + K, (*va)[QL] = vn + K;
    const double *b = qc->b, *cc = qc->cc, *dd = qc->dd, *N0 = qc->N0, *Nu = qc->Nu, *Nv = qc->Nv;
    for (int k = 0; k < K; ++k) {
        const double s = sk[k];
        LANES {
            un[k][j] = s <= 1 ? s * L->u[j] : L->u[j] + (s - 1) * (1 - L->u[j]);
            vn[k][j] = s <= 1 ? s * L->v[j] : L->v[j] + (s - 1) * (1 - L->v[j]);
        }
    }
    for (int k = 0; k < K; ++k) {
        const int hi = k + 1 < K ? k + 1 : K - 1, lo = k > 0 ? k - 1 : 0;
        LANES {
            ua[k][j] = (un[hi][j] - un[lo][j]) / 2;
            va[k][j] = (vn[hi][j] - vn[lo][j]) / 2;
        }
    }
    double S[QL], Su[QL], Sv[QL], Suv[QL];
    LANES S[j] = Su[j] = Sv[j] = Suv[j] = 0.0;
    for (int a = 0; a < K; ++a) {
        double Px[QL], Py[QL], Pz[QL], Qx[QL], Qy[QL], Qz[QL], Rx[QL], Ry[QL], Rz[QL], s0[4][QL], s1[4][QL];
        LANES {
            const double uu = un[a][j];
            Px[j] = L->p[0][0][j] + uu * b[0];
            Py[j] = L->p[0][1][j] + uu * b[1];
            Pz[j] = L->p[0][2][j] + uu * b[2];
            Qx[j] = cc[0] + uu * dd[0];
            Qy[j] = cc[1] + uu * dd[1];
            Qz[j] = cc[2] + uu * dd[2];
            Rx[j] = N0[0] + uu * Nu[0];
            Ry[j] = N0[1] + uu * Nu[1];
            Rz[j] = N0[2] + uu * Nu[2];
            s0[0][j] = s0[1][j] = s0[2][j] = s0[3][j] = 0.0;
            s1[0][j] = s1[1][j] = s1[2][j] = s1[3][j] = 0.0;
        }
        for (int l = 0; l < K; ++l) {
            double *t0 = s0[l & 3], *t1 = s1[l & 3];
            LANES {
                double vv = vn[l][j];
                double d0 = Px[j] + vv * Qx[j], d1 = Py[j] + vv * Qy[j], d2 = Pz[j] + vv * Qz[j];
                double r2 = d0 * d0 + d1 * d1 + d2 * d2;
                double Nd = (Rx[j] + vv * Nv[0]) * d0 + (Ry[j] + vv * Nv[1]) * d1 + (Rz[j] + vv * Nv[2]) * d2;
                double f = Nd * va[l][j] / (r2 * r2);
                t0[j] += f;
                t1[j] += f * vv;
            }
        }
        LANES {
            double acc0 = ((s0[0][j] + s0[1][j]) + (s0[2][j] + s0[3][j])) * ua[a][j];
            double acc1 = ((s1[0][j] + s1[1][j]) + (s1[2][j] + s1[3][j])) * ua[a][j];
            S[j] += acc0;
            Sv[j] += acc1;
            Su[j] += un[a][j] * acc0;
            Suv[j] += un[a][j] * acc1;
        }
    }
    LANES {
        om[0][j] = S[j] - Su[j] - Sv[j] + Suv[j];
        om[1][j] = Su[j] - Suv[j];
        om[2][j] = Suv[j];
        om[3][j] = Sv[j] - Suv[j];
    }
}

/* pair_weights' common case for the lanes of quad_pair_lanes and riemann_lanes (the same operations
 * in the same order lane by lane): off the quad, not flat, the quad not seen small (no Gauss blend)
 * and not near its plane. WQ: (4, QL) the quad's weights of the lanes with simple set; the others are
 * left to pair_weights. */
static void pair_lanes(const quad_lanes *L, double om[4][QL], double sizeq, double WQ[4][QL], int *simple) {
    LANES {
        const double invD = 1.0 / L->D[j];
        double wb[4], res[3], wq[4];
#define ROWDOT(i, v0, v1, v2) (L->rows[i][0][j] * (v0) + L->rows[i][1][j] * (v1) + L->rows[i][2][j] * (v2))
#define AW(w, c) (w[0] * L->p[0][c][j] + w[1] * L->p[1][c][j] + w[2] * L->p[2][c][j] + w[3] * L->p[3][c][j])
        const double m0 = L->m[0][j], m1 = L->m[1][j], m2 = L->m[2][j];
        wb[0] = ROWDOT(0, m0, m1, m2) * invD;
        wb[1] = ROWDOT(1, m0, m1, m2) * invD;
        wb[2] = ROWDOT(2, m0, m1, m2) * invD;
        wb[3] = ROWDOT(3, m0, m1, m2) * invD;
/* One refinement step of A w = m: w += A^+ (m - A w). */
#define REFINE_STEP(w)                                                                                          \
    do {                                                                                                        \
        res[0] = m0 - AW(w, 0);                                                                                 \
        res[1] = m1 - AW(w, 1);                                                                                 \
        res[2] = m2 - AW(w, 2);                                                                                 \
        for (int i = 0; i < 4; ++i) w[i] += ROWDOT(i, res[0], res[1], res[2]) * invD;                          \
    } while (0)
        REFINE_STEP(wb);
        const double k0 = L->k[0][j], k1 = L->k[1][j], k2 = L->k[2][j], k3 = L->k[3][j];
        double ok = 0, ow = 0, ww = 0;
        ok += om[0][j] * k0, ow += om[0][j] * wb[0], ww += wb[0] * wb[0];
        ok += om[1][j] * k1, ow += om[1][j] * wb[1], ww += wb[1] * wb[1];
        ok += om[2][j] * k2, ow += om[2][j] * wb[2], ww += wb[2] * wb[2];
        ok += om[3][j] * k3, ow += om[3][j] * wb[3], ww += wb[3] * wb[3];
        const double lam = ow != 0 ? ok * invD * ww / ow : 0.0;
        wq[0] = wb[0] + lam * k0;
        wq[1] = wb[1] + lam * k1;
        wq[2] = wb[2] + lam * k2;
        wq[3] = wb[3] + lam * k3;
        const double R0 = L->R[0][j], R1 = L->R[1][j], R2 = L->R[2][j], R3 = L->R[3][j];
        const double Rmax = MAX2(MAX2(R0, R1), MAX2(R2, R3)), rmin = MIN2(MIN2(R0, R1), MIN2(R2, R3));
        const int near_flat = !L->inside[j] && L->kabs[j] < NEAR_FLAT * sizeq * sizeq * Rmax;
        simple[j] = !L->redo[j] & !L->on[j] & !near_flat & !(rmin / sizeq > 31.6); /* (far_blend: 0) */
        for (int it = 0; it < REFINE; ++it) REFINE_STEP(wq);
        WQ[0][j] = wq[0], WQ[1][j] = wq[1], WQ[2][j] = wq[2], WQ[3][j] = wq[3];
#undef REFINE_STEP
#undef ROWDOT
#undef AW
    }
}

/* One pair's contribution to the point's raw weights w (the body of tc_qmvc3d's pair loop): 1 when the
 * point is on the quad (w then final), else 0. */
static inline int pair_weights(long V, const int *qi, const quad_const *qc, const quad_pair *qp, double sizeq,
                               double qtol, const double *gl, int n, const double *sk, double *un, const double *om_in,
                               double *w) {
    if (qp->vertex >= 0) {
        memset(w, 0, sizeof(double) * (size_t)V);
        w[qi[qp->vertex]] = 1.0;
        return 1;
    }
    const double(*p)[3] = qp->p, (*rows)[3] = qp->rows, *m = qp->m, *k = qp->k, *R = qp->R;
    const double *b = qp->b, *cc = qp->cc, *dd = qp->dd, *N0 = qc->N0, *Nu = qc->Nu, *Nv = qc->Nv;
    double D = qp->D, kabs = qp->kabs, u = qp->u, v = qp->v;
    int flat = qp->flat, inside = qp->inside;
    if (qp->on) {
        memset(w, 0, sizeof(double) * (size_t)V);
        w[qi[0]] += (1 - u) * (1 - v);
        w[qi[1]] += u * (1 - v);
        w[qi[2]] += u * v;
        w[qi[3]] += (1 - u) * v;
        return 1;
    }
    if (flat) return 0; /* a planar quad seen edge-on: no weight */
    double beta = far_blend(R, sizeq), wg[4], om[4];
    if (qtol > 0) {
        tc_quad_integrals(p[0], b, cc, dd, u, v, 0, qtol, gl, 0, om);
        for (int i = 0; i < 4; ++i) wg[i] = om[i];
    } else if (beta > 0) {
        gauss_weights(p[0], b, cc, dd, N0, Nu, Nv, wg);
    }
    if (beta >= 1) { /* seen small: the Gauss rule alone */
        for (int i = 0; i < 4; ++i) w[qi[i]] += wg[i];
        return 0;
    }
    /* Least-norm solution, one refinement step (Eqs. 20, 28). */
    double invD = 1.0 / D, wb[4], res[3];
    for (int i = 0; i < 4; ++i) wb[i] = dot3(rows[i], m) * invD;
    for (int c = 0; c < 3; ++c)
        res[c] = m[c] - (wb[0] * p[0][c] + wb[1] * p[1][c] + wb[2] * p[2][c] + wb[3] * p[3][c]);
    for (int i = 0; i < 4; ++i) wb[i] += dot3(rows[i], res) * invD;
    if (qtol <= 0) {
        if (om_in)
            for (int i = 0; i < 4; ++i) om[i] = om_in[i];
        else
            riemann_sums(p[0], b, cc, dd, N0, Nu, Nv, u, v, n, sk, un, om);
    }
    double ok = 0, ow = 0, ww = 0;
    for (int i = 0; i < 4; ++i) {
        ok += om[i] * k[i];
        ow += om[i] * wb[i];
        ww += wb[i] * wb[i];
    }
    double lam = qtol > 0 ? ok * invD : (ow != 0 ? ok * invD * ww / ow : 0.0);
    double wq[4];
    for (int i = 0; i < 4; ++i) wq[i] = wb[i] + lam * k[i];
    double Rmax = MAX2(MAX2(R[0], R[1]), MAX2(R[2], R[3]));
    int near_flat = !inside && kabs < NEAR_FLAT * sizeq * sizeq * Rmax;
    if (near_flat) {
        /* Near a flat quad's plane: least-norm solution from the split triangles' stable
         * weights (see _near_flat_weights in _qmvc3d.py). */
        double t1[3], t2[3], wp[4];
        triangle_weights(p[0], p[1], p[2], t1);
        triangle_weights(p[0], p[2], p[3], t2);
        wp[0] = t1[0] + t2[0];
        wp[1] = t1[1];
        wp[2] = t1[2] + t2[1];
        wp[3] = t2[2];
        if (isfinite(wp[0] + wp[1] + wp[2] + wp[3])) {
            double invn = 1.0 / sqrt(D), kh[4], pk = 0, okh = 0, ow2 = 0, ww2 = 0, wb2[4];
            for (int i = 0; i < 4; ++i) {
                kh[i] = k[i] * invn;
                pk += wp[i] * kh[i];
            }
            for (int i = 0; i < 4; ++i) {
                wb2[i] = wp[i] - pk * kh[i];
                okh += om[i] * kh[i];
                ow2 += om[i] * wb2[i];
                ww2 += wb2[i] * wb2[i];
            }
            double lam2 = qtol > 0 ? okh : (ow2 != 0 ? okh * ww2 / ow2 : 0.0);
            for (int i = 0; i < 4; ++i) wq[i] = wb2[i] + lam2 * kh[i];
            for (int it = 0; it < REFINE; ++it) {
                for (int c = 0; c < 3; ++c)
                    res[c] = (wp[0] - wq[0]) * p[0][c] + (wp[1] - wq[1]) * p[1][c] +
                             (wp[2] - wq[2]) * p[2][c] + (wp[3] - wq[3]) * p[3][c];
                for (int i = 0; i < 4; ++i) wq[i] += dot3(rows[i], res) * invD;
            }
            for (int i = 0; i < 4; ++i) w[qi[i]] += beta > 0 ? (1 - beta) * wq[i] + beta * wg[i] : wq[i];
            return 0;
        }
    }
    /* Restore A w = m (kappa's rounding error is amplified by a large lambda). */
    for (int it = 0; it < REFINE; ++it) {
        for (int c = 0; c < 3; ++c)
            res[c] = m[c] - (wq[0] * p[0][c] + wq[1] * p[1][c] + wq[2] * p[2][c] + wq[3] * p[3][c]);
        for (int i = 0; i < 4; ++i) wq[i] += dot3(rows[i], res) * invD;
    }
    for (int i = 0; i < 4; ++i) w[qi[i]] += beta > 0 ? (1 - beta) * wq[i] + beta * wg[i] : wq[i];
    return 0;
}

/*
 * P: (V, 3) vertices; quads: (Q, 4) int32; size: (Q,) longest edge or diagonal; X: (npts, 3) points;
 * tol: absolute on-cage tolerance; n: grid parameter; qtol > 0: the defining integrals to this relative
 * tolerance (tc_quad_integrals with the Gauss table gl) instead of the Riemann sum, lambda = Omega .
 * kappa / D (see qmvc3d_chunk in _qmvc3d.py). W: (npts, V) in/out: the triangles' raw weights
 * on entry (rows with on[p] = 1 are final); on exit the normalised coordinates, on[p] = 1 for the
 * points on the cage.
 */
/* One cage of tc_qmvc3d's batch; returns 1 when a thread could not allocate its scratch. */
static int qmvc3d_one(const double *P, long V, const int *quads, long Q, const double *size, const double *X, long npts,
                      double tol, int n, double qtol, const double *gl, int nthreads, double *W, unsigned char *on) {
    const int K = 2 * n + 1, KP = (K + 3) & ~3;
    double centre[3];
    const double far2 = tc_far_centre(P, V, 3, 1, 3, centre);
    /* The quads' point-independent constants, once (without the table, per pair). */
    quad_const *QC = (quad_const *)malloc(sizeof(quad_const) * (size_t)(Q > 0 ? Q : 1));
    if (QC)
        for (long q = 0; q < Q; ++q) tc_quad_const(P, quads + 4 * q, QC + q);
    int failed = 0; /* a thread could not allocate its scratch */
#pragma omp parallel num_threads(nthreads)
    {
        double *un = (double *)malloc(sizeof(double) * (4 * (size_t)KP + (size_t)K + 4 * (size_t)K * QL));
        if (!un) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp barrier
        if (failed) goto done; /* (every thread: none enters a worksharing loop) */
        double *sk = un + 4 * KP, *ln = sk + K;
        for (int k = 0; k < K; ++k) sk[k] = (double)k / n;
        if (qtol > 0 || !QC) {
#pragma omp for schedule(dynamic, 16)
            for (long pt = 0; pt < npts; ++pt) {
                double *w = W + pt * V;
                if (on[pt]) continue;
                const double *x = X + 3 * pt;
                for (long q = 0; q < Q && !on[pt]; ++q) {
                    const int *qi = quads + 4 * q;
                    quad_pair qp;
                    quad_const qloc;
                    const quad_const *qc = QC ? QC + q : (tc_quad_const(P, qi, &qloc), &qloc);
                    /* The projection serves only the first split of the quadrature and the on-quad
                     * test: a quad integrated whole is far from the point (see tc_quad_whole). */
                    int project = !(qtol > 0) || !tc_quad_whole(P, qi, x, qtol);
                    tc_quad_pair_c(P, qi, qc, x, tol, project, &qp);
                    if (pair_weights(V, qi, qc, &qp, size[q], qtol, gl, n, sk, un, NULL, w)) {
                        on[pt] = 1;
                        break;
                    }
                }
                if (on[pt]) continue;
                double inv = 1.0 / tc_mv_total(w, V, P, 3, 1, 3, x, centre, far2);
                for (long c = 0; c < V; ++c) w[c] *= inv;
            }
        } else {
            /* The Riemann form: QL points for one quad side by side (quad_pair_lanes), then each
             * lane's pair as above. */
            const long nblk = (npts + QL - 1) / QL;
#pragma omp for schedule(dynamic, 4)
            for (long blk = 0; blk < nblk; ++blk) {
                const long p0 = blk * QL;
                const int nl = npts - p0 < QL ? (int)(npts - p0) : QL;
                int act[QL], nact = 0;
                for (int j = 0; j < QL; ++j) {
                    act[j] = j < nl && !on[p0 + j];
                    nact += act[j];
                }
                quad_lanes L;
                for (long q = 0; q < Q && nact > 0; ++q) {
                    const int *qi = quads + 4 * q;
                    const quad_const *qc = QC + q;
                    quad_pair_lanes(P, qi, qc, X + 3 * p0, nl, tol, &L);
                    double om4[4][QL], omr[QL][4];
                    riemann_lanes(qc, &L, n, sk, ln, om4);
                    for (int j = 0; j < QL; ++j)
                        for (int i = 0; i < 4; ++i) omr[j][i] = om4[i][j];
                    double WQ[4][QL];
                    int simple[QL];
                    pair_lanes(&L, om4, size[q], WQ, simple);
                    for (int j = 0; j < nl; ++j) {
                        if (!act[j]) continue;
                        const long pt = p0 + j;
                        if (simple[j]) {
                            double *w = W + pt * V;
                            for (int i = 0; i < 4; ++i) w[qi[i]] += WQ[i][j];
                            continue;
                        }
                        quad_pair qp;
                        if (L.redo[j]) {
                            tc_quad_pair_c(P, qi, qc, X + 3 * pt, tol, 1, &qp);
                        } else {
                            for (int i = 0; i < 4; ++i) {
                                for (int c = 0; c < 3; ++c) {
                                    qp.p[i][c] = L.p[i][c][j];
                                    qp.rows[i][c] = L.rows[i][c][j];
                                }
                                qp.R[i] = L.R[i][j];
                                qp.k[i] = L.k[i][j];
                            }
                            for (int c = 0; c < 3; ++c) {
                                qp.m[c] = L.m[c][j];
                                qp.b[c] = qc->b[c];
                                qp.cc[c] = qc->cc[c];
                                qp.dd[c] = qc->dd[c];
                            }
                            qp.D = L.D[j];
                            qp.kabs = L.kabs[j];
                            qp.u = L.u[j];
                            qp.v = L.v[j];
                            qp.flat = 0;
                            qp.inside = L.inside[j];
                            qp.vertex = -1;
                            qp.on = L.on[j];
                        }
                        if (pair_weights(V, qi, qc, &qp, size[q], qtol, gl, n, sk, un, L.redo[j] ? NULL : omr[j], W + pt * V)) {
                            on[pt] = 1;
                            act[j] = 0;
                            --nact;
                        }
                    }
                }
                for (int j = 0; j < nl; ++j) {
                    const long pt = p0 + j;
                    if (on[pt]) continue;
                    double *w = W + pt * V;
                    double inv = 1.0 / tc_mv_total(w, V, P, 3, 1, 3, X + 3 * pt, centre, far2);
                    for (long c = 0; c < V; ++c) w[c] *= inv;
                }
            }
        }
    done:
        free(un);
    }
    free(QC);
    return failed;
}

/* Quad mean value coordinates of a batch of B cages with one topology (vertices P (B, V, 3), the
 * quads' sizes (B, Q), on-cage tolerances tol (B,)): points X (XB, npts, 3), XB = 1 (shared by every
 * cage) or B; the quads' raw weights added into W (B, npts, V) (the triangles' raw weights, from
 * tc_mvc3d, already there), then each row normalised; rows flagged in on (B, npts) hold their
 * on-cage values and are skipped. The cages one after the other, each parallel over its points. A
 * failed allocation sets every flag to 3 (and W to NaN). XB must be 1 or B (the glue checks). */
void tc_qmvc3d(long B, const double *P, long V, const int *quads, long Q, const double *size, const double *X, long XB,
               long npts, const double *tol, int n, double qtol, const double *gl, int nthreads, double *W,
               unsigned char *on) {
    int failed = 0;
    for (long b = 0; b < B && !failed; ++b)
        failed = qmvc3d_one(P + b * V * 3, V, quads, Q, size + b * Q, X + (XB > 1 ? b : 0) * npts * 3, npts, tol[b], n,
                            qtol, gl, nthreads, W + b * npts * V, on + b * npts);
    if (failed) { /* the glue's sign of a failed allocation (it raises MemoryError) */
        for (long k = 0; k < B * npts * V; ++k) W[k] = NAN;
        memset(on, 3, (size_t)(B * npts)); /* (WORKSPACE_FAILED: NaN rows also mean a vanishing total) */
    }
}
