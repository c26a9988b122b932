/*
 * The joint vector-Jacobian product of 3D mean value coordinates (mvc3d_vjp.c) for points near a
 * face's support plane, split per face (float64). The product splits over faces once the
 * normalisation is done: lam = w / W, wbar_v = (gbar_v - gbar . lam) / W, and each face's corner
 * weights depend on x and its own three vertices only. For each point this kernel
 *
 *   1. computes every face's corner weights: the direct vector form on the *regular* pairs (the
 *      test of mvc3d_vjp.c), the stable split form (tc_stable_face) on the pairs near the face's
 *      support plane (*careful* pairs), hence W, lam and wbar;
 *   2. runs the hand-derived adjoint of mvc3d_vjp.c over the regular pairs (into GX and GP);
 *   3. differentiates the split form of the careful pairs by forward mode in the nine components
 *      of the face's a_i (dual_split_face: the operations of kernel3d._stable_face_weights), with
 *      the coefficient of dh of the c_i / h term of the nearest face holding the foot point (f*)
 *      taken from the identity sum_v wbar_v w_v = 0 (no cancellation: see ops._split_vjp). Other
 *      faces holding the foot point (near an edge: both adjacent faces may) differentiate their
 *      c_i / h as it is; the one identity cannot split between two faces, and near an edge the
 *      inputs' own rounding (n . (a_j x a_k) of an edge at distance d) already costs eps / d,
 *      which is what that term loses. With split_pairs = 0 it leaves the careful pairs to the
 *      caller (ops._split_vjp, autograd of the torch split form: the tests compare the two): PAIR
 *      marks them (1; 2 for f*, 3 for the other faces around the foot), WB holds wbar, HS the h of
 *      f* and SN = sum over every face but f* of wbar . w_f.
 *
 * A point takes this path (status 1) only when every face is regular or careful. Points on the
 * cage take the interpolant's closed form (status 2), as tc_mvcd3d and ops._on_face_vjp define it:
 * the largest face within tol of the point (tc_mvcd3d's test, with its near_d and far_d; of areas
 * within TC_AREA_TIE of each other the first, as the torch kernel), or a corner within tol. In that
 * face or on its edge, with b_i its barycentric coordinates (clamped at 0 and renormalised:
 * tc_mvcd3d's values, unclamped, differ from them by rounding),
 * GX = sum_i gbar_i (E_i x n) / (2 area) and GP_i -= b_i GX (d lam_v / d p_j = -lam_j d lam_v / dx:
 * the interpolant is affine invariant); at a vertex nothing (lam is constant). On an edge the
 * coordinates have a kink: GX and GP are both the derivatives of that one face's interpolant, so
 * that they agree with each other (a common translation of the point and the cage changes nothing:
 * GX + sum_j GP_j = 0) and with autograd of the torch kernel.
 *
 * Every other point is left to the caller's general path (status 0, nothing accumulated): seeing
 * a thin face from a few widths or a face below 1/far_always of its distance, with face weights
 * that cancel (far outside), with the foot point on an edge's line to rounding (the two forms
 * would split c_i / h differently), or within band times its distance to the nearest vertex of
 * the line of an edge outside the edge (ops._edge_line_offsets' rule, for which band is
 * EDGE_LINE_BAND: a superset of the points that rule takes).
 *
 * P (V, 3) vertices; tri (T, 3) int32 corners; X (n, 3) points; G (n, V) the cotangent dL/dlam.
 * Outputs (rows of points with status 0 are zero): GX (n, 3), GP (V, 3) summed over the points
 * with status 1 or 2, status (n,), PAIR (n, T), WB (n, V), SN (n,), HS (n,).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

#define NEAR_TWO_PI 6.283185307179586476925286766559

/* Per-face scratch: a (9), N (9), |N| (3), d (3), theta (3), g (3), m (3), det, w (3), h, kind. */
enum { Q_A = TC_FA_A, Q_N = TC_FA_N, Q_NN = TC_FA_NN, Q_D = TC_FA_D, Q_TH = TC_FA_TH, Q_G = TC_FA_G, Q_M = TC_FA_M,
       Q_DET = TC_FA_DET, Q_W = TC_FA_W, Q_H = TC_FA_SIZE, Q_KIND = TC_FA_SIZE + 1, Q_SIZE = TC_FA_SIZE + 2 };

/* Per-face constants: unit normal (3), edge lengths ell (3, opposite each corner), gram (9), twice
 * the area, the longest edge. */
enum { F_N = 0, F_ELL = 3, F_GRAM = 6, F_TWO_AREA = 15, F_LONGEST = 16, F_SIZE = 17 };

/* Forward-mode derivatives with respect to the nine components of a face's a_i = p_i - x (those
 * of x are minus their sum over the corners): a value and its nine partial derivatives. */
typedef struct {
    double v, d[9];
} dual9;

static inline dual9 d_const(double v) {
    dual9 r;
    r.v = v;
    for (int k = 0; k < 9; ++k) r.d[k] = 0.0;
    return r;
}
static inline dual9 d_add(dual9 a, dual9 b) {
    a.v += b.v;
    for (int k = 0; k < 9; ++k) a.d[k] += b.d[k];
    return a;
}
static inline dual9 d_sub(dual9 a, dual9 b) {
    a.v -= b.v;
    for (int k = 0; k < 9; ++k) a.d[k] -= b.d[k];
    return a;
}
static inline dual9 d_scale(dual9 a, double c) {
    a.v *= c;
    for (int k = 0; k < 9; ++k) a.d[k] *= c;
    return a;
}
static inline dual9 d_mul(dual9 a, dual9 b) {
    dual9 r;
    r.v = a.v * b.v;
    for (int k = 0; k < 9; ++k) r.d[k] = a.d[k] * b.v + a.v * b.d[k];
    return r;
}
static inline dual9 d_div(dual9 a, dual9 b) {
    dual9 r;
    r.v = a.v / b.v;
    for (int k = 0; k < 9; ++k) r.d[k] = (a.d[k] - r.v * b.d[k]) / b.v;
    return r;
}
static inline dual9 d_sqrt(dual9 a) { /* (a.v > 0) */
    dual9 r;
    r.v = sqrt(a.v);
    for (int k = 0; k < 9; ++k) r.d[k] = a.d[k] / (2.0 * r.v);
    return r;
}
static inline dual9 d_atan2(dual9 y, dual9 x) {
    dual9 r;
    double q = x.v * x.v + y.v * y.v;
    r.v = atan2(y.v, x.v);
    for (int k = 0; k < 9; ++k) r.d[k] = q > 0 ? (x.v * y.d[k] - y.v * x.d[k]) / q : 0.0;
    return r;
}
static inline dual9 d_dot(const dual9 *a, const dual9 *b) {
    return d_add(d_add(d_mul(a[0], b[0]), d_mul(a[1], b[1])), d_mul(a[2], b[2]));
}
static inline void d_cross(const dual9 *a, const dual9 *b, dual9 *c) {
    c[0] = d_sub(d_mul(a[1], b[2]), d_mul(a[2], b[1]));
    c[1] = d_sub(d_mul(a[2], b[0]), d_mul(a[0], b[2]));
    c[2] = d_sub(d_mul(a[0], b[1]), d_mul(a[1], b[0]));
}

/* The split form of one face's weights with their derivatives in a (9,): w_i = r_i + c_i / h, as
 * _stable_face_weights in families/mean_value/kernel3d.py (the same operations, so that the
 * derivatives are autograd's of it), its regular part r, its singular part c (zero where the
 * face does not hold the foot point) and h, all as dual numbers. */
static void dual_split_face(const double *a_in, dual9 *r, dual9 *c, dual9 *hout) {
    dual9 a[3][3], E[3][3], e1[3], e2[3], cr[3], nrm[3];
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) {
            a[i][k] = d_const(a_in[3 * i + k]);
            a[i][k].d[3 * i + k] = 1.0;
        }
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) E[i][k] = d_sub(a[(i + 1) % 3][k], a[(i + 2) % 3][k]);
    for (int k = 0; k < 3; ++k) e1[k] = d_sub(a[1][k], a[0][k]), e2[k] = d_sub(a[2][k], a[0][k]);
    d_cross(e1, e2, cr);
    dual9 two_area = d_sqrt(d_dot(cr, cr));
    for (int k = 0; k < 3; ++k) nrm[k] = d_div(cr[k], two_area);
    dual9 h = d_dot(nrm, a[0]), h2 = d_mul(h, h);
    dual9 sv[3], ell[3], t_over_N[3], S_rest = d_const(0.0);
    double wind_angle = 0.0;
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        dual9 Ne[3];
        d_cross(a[j], a[k], Ne);
        sv[e] = d_dot(nrm, Ne);
        ell[e] = d_sqrt(d_dot(E[e], E[e]));
    }
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        double sigma = sv[e].v >= 0 ? 1.0 : -1.0;
        dual9 s_abs = d_scale(sv[e], sigma), dots = d_dot(a[j], a[k]);
        s_abs.v += 0.0;
        dual9 qq = d_sub(dots, h2), l2 = d_mul(ell[e], ell[e]);
        dual9 N2 = d_add(d_mul(sv[e], sv[e]), d_mul(h2, l2));
        dual9 N = N2.v > 0 ? d_sqrt(N2) : d_const(0.0);
        dual9 theta0 = d_atan2(s_abs, qq);
        wind_angle += sigma * theta0.v;
        dual9 Nps = d_add(N, s_abs);
        dual9 safe_Nps = Nps.v > 0 ? Nps : d_const(1.0);
        dual9 X = d_sub(d_div(d_mul(qq, l2), safe_Nps), s_abs);
        dual9 Y = d_add(d_mul(dots, qq), d_mul(N, s_abs));
        dual9 delta = d_atan2(d_mul(h2, X), Y);
        dual9 delta_h2 = h2.v > 0 ? d_div(delta, h2) : d_div(X, Y);
        dual9 theta = d_add(theta0, delta);
        dual9 safe_N = N.v > 0 ? N : d_const(1.0);
        if (N.v > 0) {
            t_over_N[e] = d_div(theta, safe_N);
        } else { /* 1 / (R_j R_k) */
            dual9 Rj = d_sqrt(d_dot(a[j], a[j])), Rk = d_sqrt(d_dot(a[k], a[k]));
            t_over_N[e] = d_div(d_const(1.0), d_mul(Rj, Rk));
        }
        dual9 eps_h2 = d_div(l2, d_mul(safe_N, safe_Nps));
        S_rest = d_add(S_rest, d_scale(d_sub(delta_h2, d_mul(theta, eps_h2)), sigma));
    }
    double wind = nearbyint(wind_angle / NEAR_TWO_PI);
    dual9 inv4A = d_div(d_const(1.0), d_scale(two_area, 2.0));
    for (int i = 0; i < 3; ++i) {
        dual9 B = d_mul(sv[i], S_rest);
        for (int e = 0; e < 3; ++e) B = d_add(B, d_mul(t_over_N[e], d_dot(E[i], E[e])));
        r[i] = d_mul(d_mul(h, B), inv4A);
        c[i] = wind != 0 ? d_scale(d_mul(sv[i], inv4A), NEAR_TWO_PI * wind) : d_const(0.0);
    }
    *hout = h;
}

/* A workspace not allocated: no point taken (status 0) and no pair left (PAIR 0), every output
 * zero: the caller computes every point by its fallback. */
static void vjp_near_failed(long V, long T, long n, double *GX, double *GP, unsigned char *status, unsigned char *PAIR,
                            double *WB, double *SN, double *HS) {
    memset(GX, 0, sizeof(double) * 3 * (size_t)n);
    memset(GP, 0, sizeof(double) * 3 * (size_t)V);
    memset(status, 0, (size_t)n);
    memset(PAIR, 0, (size_t)n * (size_t)T);
    memset(WB, 0, sizeof(double) * (size_t)n * (size_t)V);
    memset(SN, 0, sizeof(double) * (size_t)n);
    memset(HS, 0, sizeof(double) * (size_t)n);
}

void tc_mvc3d_vjp_near(const double *P, long V, const int *tri, long T, const double *X, long n, const double *G,
                       double tol, double near_c, double cancel_c, double far_always, double band, double near_d,
                       double far_d, int split_pairs, int nthreads, double *GX, double *GP,
                       unsigned char *status, unsigned char *PAIR, double *WB, double *SN, double *HS) {
    double *fc = (double *)malloc(sizeof(double) * F_SIZE * (size_t)(T > 0 ? T : 1));
    if (fc == NULL) {
        vjp_near_failed(V, T, n, GX, GP, status, PAIR, WB, SN, HS);
        return;
    }
    int any_thin = 0;
    for (long f = 0; f < T; ++f) {
        const double *p[3] = {P + 3 * tri[3 * f], P + 3 * tri[3 * f + 1], P + 3 * tri[3 * f + 2]};
        double *c = fc + F_SIZE * f, E[3][3], e1[3], e2[3], cr[3];
        for (int i = 0; i < 3; ++i)
            for (int k = 0; k < 3; ++k) E[i][k] = p[(i + 1) % 3][k] - p[(i + 2) % 3][k];
        for (int k = 0; k < 3; ++k) e1[k] = p[1][k] - p[0][k], e2[k] = p[2][k] - p[0][k];
        cross3(e1, e2, cr);
        double ta = sqrt(dot3(cr, cr)), l = 0.0;
        for (int k = 0; k < 3; ++k) c[F_N + k] = ta > 0 ? cr[k] / ta : 0.0;
        for (int i = 0; i < 3; ++i) {
            c[F_ELL + i] = sqrt(dot3(E[i], E[i]));
            l = fmax(l, dot3(E[i], E[i]));
            for (int e = 0; e < 3; ++e) c[F_GRAM + 3 * i + e] = dot3(E[i], E[e]);
        }
        c[F_TWO_AREA] = ta;
        c[F_LONGEST] = sqrt(l);
        any_thin |= ta > 0 && l > TC_THIN_ASPECT * ta;
    }
    memset(GP, 0, sizeof(double) * 3 * (size_t)V);
    int failed = 0; /* a thread could not allocate its scratch */
#pragma omp parallel num_threads(nthreads)
    {
        double *S = (double *)malloc(sizeof(double) * ((size_t)Q_SIZE * (size_t)T + 5 * (size_t)V));
        if (S == NULL) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp barrier
        if (failed) goto done; /* (every thread: none enters the worksharing loop) */
        double *Wv = S + (size_t)Q_SIZE * T, *gp = Wv + V, *scratch_gx = gp + 3 * V;
        memset(gp, 0, sizeof(double) * 3 * (size_t)V);
#pragma omp for schedule(dynamic, 8)
        for (long p = 0; p < n; ++p) {
            const double *x = X + 3 * p;
            const double *g = G + p * V;
            double *wbar = WB + p * V, *gx = scratch_gx;
            unsigned char *pair = PAIR + p * T;
            memset(wbar, 0, sizeof(double) * (size_t)V);
            memset(pair, 0, (size_t)T);
            GX[3 * p] = GX[3 * p + 1] = GX[3 * p + 2] = 0.0;
            status[p] = 0;
            SN[p] = HS[p] = 0.0;
            memset(Wv, 0, sizeof(double) * (size_t)V);
            double L = INFINITY; /* distance to the nearest vertex */
            for (long v = 0; v < V; ++v) {
                double a[3] = {P[3 * v] - x[0], P[3 * v + 1] - x[1], P[3 * v + 2] - x[2]};
                L = fmin(L, sqrt(dot3(a, a)));
            }
            int ok = 1;
            long fstar = -1, onf = -1, onv = -1;
            double abs_sum = 0.0;
            for (long f = 0; f < T && ok; ++f) {
                const double *c = fc + F_SIZE * f;
                double *s = S + (size_t)Q_SIZE * f, *a = s + Q_A, *N = s + Q_N, *m = s + Q_M, *w = s + Q_W;
                double R[3], rmin = tc_mvc_face_direct(P, tri + 3 * f, x, s, R), det = s[Q_DET];
                const double two_area = c[F_TWO_AREA];
                /* on the cage, as tc_mvcd3d (whose values and derivatives the general path takes
                 * there): the first face, in order, whose corner is within tol, or which holds
                 * the point within tol (its near-plane test, far faces skipped); below, the
                 * largest face that holds it */
                if (rmin <= tol) {
                    onv = tri[3 * f + (R[0] <= tol ? 0 : (R[1] <= tol ? 1 : 2))];
                    break;
                }
                if (!(c[F_LONGEST] <= far_d * rmin)) {
                    double h = dot3(c + F_N, a);
                    int in_prism = fabs(h) <= tol && fabs(h) < near_d * rmin;
                    for (int e = 0; e < 3 && in_prism; ++e) in_prism = dot3(c + F_N, N + 3 * e) >= -tol * c[F_ELL + e];
                    if (in_prism) {
                        onf = f;
                        break;
                    }
                }
                if (!(c[F_LONGEST] * far_always >= rmin) ||
                    (any_thin && c[F_LONGEST] * c[F_LONGEST] > TC_THIN_ASPECT * two_area &&
                     tc_thin_face((const double(*)[3])a, two_area))) {
                    ok = 0;
                    break;
                }
                if (fabs(det) >= near_c * rmin * two_area) { /* regular: the direct form */
                    s[Q_KIND] = 0.0;
                    for (int i = 0; i < 3; ++i) w[i] = dot3(N + 3 * i, m) / det;
                } else { /* careful: the split form */
                    const double *nrm = c + F_N, *ell = c + F_ELL;
                    double h = dot3(nrm, a), sv[3], dots[3], wind_angle = 0.0;
                    int inside = 1;
                    for (int e = 0; e < 3; ++e) {
                        int j = (e + 1) % 3, k = (e + 2) % 3;
                        sv[e] = dot3(nrm, N + 3 * e);
                        dots[e] = s[Q_D + e];
                        inside &= sv[e] >= -tol * ell[e];
                        /* the foot point on an edge's line to rounding: the two forms may see it on
                         * either side (and so split c_i / h differently) */
                        if (fabs(sv[e]) <= 1e-10 * R[j] * R[k]) ok = 0;
                        double qq = dots[e] - h * h, sa = fabs(sv[e]);
                        wind_angle += (sv[e] >= 0 ? 1.0 : -1.0) * atan2(sa, qq);
                        /* the line of edge e outside the edge, within band * L (ops._edge_line_offsets) */
                        const double *pj = P + 3 * tri[3 * f + j], *pk = P + 3 * tri[3 * f + k];
                        double u[3], rel[3], uu, t, r2 = 0.0;
                        for (int q = 0; q < 3; ++q) u[q] = pk[q] - pj[q], rel[q] = x[q] - pj[q];
                        uu = dot3(u, u);
                        t = uu > 0 ? dot3(rel, u) / uu : 0.0;
                        for (int q = 0; q < 3; ++q) r2 += (rel[q] - t * u[q]) * (rel[q] - t * u[q]);
                        if ((t < 0 || t > 1) && sqrt(r2) < band * L) ok = 0;
                    }
                    if (fabs(h) <= tol && inside) ok = 0; /* on the face (by the test above: rounding) */
                    double turns = wind_angle / NEAR_TWO_PI, wind = nearbyint(turns);
                    if (fabs(turns - wind) > 0.25) ok = 0;
                    if (!ok) break;
                    tc_stable_face(h, sv, dots, R, ell, c + F_GRAM, two_area, w);
                    s[Q_H] = h;
                    if (wind != 0) { /* f* is the nearest face around the foot point, the others kind 3 */
                        s[Q_KIND] = 2.0;
                        if (fstar < 0) {
                            fstar = f;
                        } else if (fabs(h) < fabs(S[(size_t)Q_SIZE * fstar + Q_H])) {
                            S[(size_t)Q_SIZE * fstar + Q_KIND] = 3.0;
                            fstar = f;
                        } else {
                            s[Q_KIND] = 3.0;
                        }
                    } else {
                        s[Q_KIND] = 1.0;
                    }
                }
                double fsum = 0.0;
                for (int i = 0; i < 3; ++i) {
                    Wv[tri[3 * f + i]] += w[i];
                    fsum += w[i];
                }
                abs_sum += fabs(fsum);
            }
            if (!ok) continue;
            if (onf >= 0 || onv >= 0) { /* on the cage */
                for (long f = 0; f < T && ok; ++f) /* (ops._edge_line_offsets' rule: the general path) */
                    for (int e = 0; e < 3 && ok; ++e) {
                        const double *pj = P + 3 * tri[3 * f + (e + 1) % 3], *pk = P + 3 * tri[3 * f + (e + 2) % 3];
                        double u[3], rel[3], uu, t, r2 = 0.0;
                        for (int q = 0; q < 3; ++q) u[q] = pk[q] - pj[q], rel[q] = x[q] - pj[q];
                        uu = dot3(u, u);
                        t = uu > 0 ? dot3(rel, u) / uu : 0.0;
                        for (int q = 0; q < 3; ++q) r2 += (rel[q] - t * u[q]) * (rel[q] - t * u[q]);
                        if ((t < 0 || t > 1) && sqrt(r2) < band * L && L > 0) ok = 0;
                    }
                if (!ok) continue;
                if (onv >= 0) { /* at a vertex: lam is constant, no derivatives */
                    status[p] = 2;
                    continue;
                }
                for (long f = onf + 1; f < T; ++f) { /* the largest face holding it (as tc_mvcd3d) */
                    const double *c = fc + F_SIZE * f, *q[3] = {P + 3 * tri[3 * f], P + 3 * tri[3 * f + 1],
                                                                P + 3 * tri[3 * f + 2]};
                    double a[3][3], rmin = INFINITY;
                    for (int i = 0; i < 3; ++i) {
                        for (int k = 0; k < 3; ++k) a[i][k] = q[i][k] - x[k];
                        rmin = fmin(rmin, sqrt(dot3(a[i], a[i])));
                    }
                    double h = fabs(dot3(c + F_N, a[0]));
                    if (c[F_TWO_AREA] > fc[F_SIZE * onf + F_TWO_AREA] * (1 + TC_AREA_TIE) &&
                        !(c[F_LONGEST] <= far_d * rmin) && h <= tol && h < near_d * rmin &&
                        tc_in_face_prism((const double(*)[3])a, c + F_N, c + F_ELL, tol))
                        onf = f;
                }
                /* in a face or on its edge: its barycentric coordinates b_i = n . (a_j x a_k) /
                 * (2 area) (clamped at 0 and renormalised, as the values), their gradients
                 * (E_i x n) / (2 area) */
                const double *c = fc + F_SIZE * onf;
                double b[3], bsum = 0.0, gxf[3] = {0, 0, 0};
                for (int i = 0; i < 3; ++i) {
                    const double *pj = P + 3 * tri[3 * onf + (i + 1) % 3], *pk = P + 3 * tri[3 * onf + (i + 2) % 3];
                    double E[3], En[3], aj[3], ak[3], Ne[3];
                    for (int q = 0; q < 3; ++q) E[q] = pj[q] - pk[q], aj[q] = pj[q] - x[q], ak[q] = pk[q] - x[q];
                    cross3(E, c + F_N, En);
                    cross3(aj, ak, Ne);
                    b[i] = fmax(dot3(c + F_N, Ne) / c[F_TWO_AREA], 0.0);
                    bsum += b[i];
                    for (int q = 0; q < 3; ++q) gxf[q] += g[tri[3 * onf + i]] * En[q] / c[F_TWO_AREA];
                }
                if (!(bsum > 0.0)) continue;
                for (int i = 0; i < 3; ++i) b[i] /= bsum;
                status[p] = 2;
                for (int q = 0; q < 3; ++q) GX[3 * p + q] = gxf[q];
                for (int i = 0; i < 3; ++i)
                    for (int q = 0; q < 3; ++q) gp[3 * tri[3 * onf + i] + q] -= b[i] * gxf[q];
                continue;
            }
            double total = 0.0;
            for (long v = 0; v < V; ++v) total += Wv[v];
            if (!(abs_sum <= cancel_c * fabs(total)) || total == 0.0 || !isfinite(total)) continue;
            status[p] = 1;
            double sg = 0.0;
            for (long v = 0; v < V; ++v) sg += g[v] * Wv[v];
            sg /= total;
            for (long v = 0; v < V; ++v) wbar[v] = (g[v] - sg) / total;
            gx[0] = gx[1] = gx[2] = 0.0;
            double sn = 0.0;
            for (long f = 0; f < T; ++f) {
                const double *s = S + (size_t)Q_SIZE * f, *w = s + Q_W;
                if (f != fstar)
                    for (int i = 0; i < 3; ++i) sn += wbar[tri[3 * f + i]] * w[i];
                if (s[Q_KIND] != 0.0) {
                    pair[f] = (unsigned char)s[Q_KIND];
                    continue;
                }
                tc_mvc_face_adjoint(s, tri + 3 * f, wbar, gp, gx); /* the direct form's adjoint */
            }
            /* the careful pairs: forward-mode derivatives of their split form. Where the face
             * holds the foot point (f*), w = r + c / h: the coefficient of dh, -(wbar . c) / h^2,
             * is taken as (sn + wbar . r) / h (sum_v wbar_v w_v = 0), free of the cancellation of
             * -c dh / h^2 against wbar ~ h. */
            const double h0 = fstar >= 0 ? S[(size_t)Q_SIZE * fstar + Q_H] : 1.0;
            for (long f = 0; f < T && split_pairs; ++f) {
                const double *s = S + (size_t)Q_SIZE * f;
                if (s[Q_KIND] == 0.0) continue;
                dual9 r[3], c[3], h;
                dual_split_face(s + Q_A, r, c, &h);
                double wb[3], dl[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, wr = 0.0;
                for (int i = 0; i < 3; ++i) {
                    wb[i] = wbar[tri[3 * f + i]];
                    wr += wb[i] * r[i].v;
                    for (int k = 0; k < 9; ++k) dl[k] += wb[i] * r[i].d[k];
                }
                if (f == fstar) {
                    double beta = (sn + wr) / h0;
                    for (int k = 0; k < 9; ++k) {
                        dl[k] += beta * h.d[k];
                        for (int i = 0; i < 3; ++i) dl[k] += wb[i] / h0 * c[i].d[k];
                    }
                } else if (s[Q_KIND] == 3.0) { /* another face around the foot: c / h as it is */
                    double wc = wb[0] * c[0].v + wb[1] * c[1].v + wb[2] * c[2].v, hf = h.v;
                    for (int k = 0; k < 9; ++k) {
                        dl[k] -= wc / (hf * hf) * h.d[k];
                        for (int i = 0; i < 3; ++i) dl[k] += wb[i] / hf * c[i].d[k];
                    }
                }
                for (int i = 0; i < 3; ++i) {
                    double *dst = gp + 3 * tri[3 * f + i];
                    for (int q = 0; q < 3; ++q) {
                        dst[q] += dl[3 * i + q];
                        gx[q] -= dl[3 * i + q];
                    }
                }
                pair[f] = 0;
            }
            for (int c = 0; c < 3; ++c) GX[3 * p + c] = gx[c];
            SN[p] = sn;
            HS[p] = fstar >= 0 ? S[(size_t)Q_SIZE * fstar + Q_H] : 0.0;
        }
#pragma omp critical
        for (long k = 0; k < 3 * V; ++k) GP[k] += gp[k];
    done:
        free(S);
    }
    free(fc);
    if (failed) vjp_near_failed(V, T, n, GX, GP, status, PAIR, WB, SN, HS);
}
