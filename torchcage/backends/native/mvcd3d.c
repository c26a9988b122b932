/* Analytic gradients and Hessians of 3D mean value coordinates (closed triangle cages).
 *
 * For each point x and face T with corners p_1..p_3 (a_i = p_i - x), the face weights
 * w_i^T (Ju et al.; vector form of Thiery et al. 2014, Sec. 2.2) and their first and second
 * derivatives are summed per vertex, then normalised: with W = sum w,
 *   lam = w / W,  grad lam = (grad w - lam grad W) / W,
 *   H lam = (H w - lam H W - grad lam grad W^T - grad W grad lam^T) / W.
 * Three evaluations of a face, chosen per pair (see families/mean_value/derivatives.py):
 *
 * 1. direct (default). From sum_j w_j a_j = m (m = sum_e g_e N_e, N_e = a_{e+1} x a_{e+2},
 *    g_e = theta_e / (2 |N_e|)) and da_j/dx = -I:
 *        U dw/dx_c = dm/dx_c + W e_c,   U d2w/dx_c dx_d = d2m/dx_c dx_d + dW/dx_d e_c + dW/dx_c e_d,
 *    with U = [a_1 a_2 a_3] and U^-1 = rows N_i / det (det = 2 area h). N_e is affine in x
 *    (dN_e/dx_c = e_c x E_e, E_e = p_{e+1} - p_{e+2}), so only the scalars g_e need jets: g is a
 *    function of u = |N|^2 and v = a_{e+1}.a_{e+2}, g = G(u / v^2) / (2 v) with
 *    G(t) = atan(sqrt t)/sqrt t = int_0^1 dy / (1 + t y^2) (Gauss-Legendre, exact to rounding for
 *    t <= 1) while the angle is below 45 degrees, else atan2(sqrt u, v) / (2 sqrt u).
 * 2. near the face's support plane (|h| < near_c min |a_i|, not on the face): the split form of
 *    mvc3d.c (h, s_e = n.N_e, q_j.q_k are polynomials in x), every term carrying its power of h
 *    explicitly, evaluated with jets. For an edge seen under a small angle (q_j.q_k > 0 and
 *    s^2 < 0.64 (q_j.q_k)^2) the two O(1/|N|) terms of the split form cancel; there the
 *    difference is rewritten as
 *        (theta |s| / N - theta_0) / (|s| h^2) = -G(U)/(d qq) + G[U, u] (l^2 qq^2 - 2 s^2 qq - s^2 h^2) / (d^2 qq^3)
 *    (U = N^2/d^2, u = s^2/qq^2, d = a_j.a_k, qq = d - h^2, G[U, u] the divided difference
 *    -int_0^1 y^2 / ((1 + U y^2)(1 + u y^2)) dy), smooth through the edge's support line.
 * 3. far field (longest edge <= far_c min |a_i|): w_i^T = int_T phi_i h / |p - x|^4 dA by a
 *    collapsed Gauss rule, differentiated under the integral.
 * 4. thin faces seen from a few widths (tc_thin_face): the same integral swept as in
 *    _core/thin_triangle.py (Gauss across the width; along each segment 16-point rules on
 *    panels graded towards the point, none longer than its distance), differentiated under the
 *    integral. The other forms' terms there are length / width times the face's share and cancel
 *    (a sliver of width 1e-9 left the gradients off by 3e-6 relative).
 * Points on a face (within tol) have no derivatives: they are flagged in `on`.
 *
 * Near a face (foot point inside it, small h) that face's weights carry the singular part
 * k s_i / h (k = 2 pi / (4 area), s_i / (2 area) the foot's barycentric coordinates), and the
 * quotient w / W would subtract derivatives of size 1/h^3 to get O(1) ones. For the nearest such
 * face the singular part is kept apart and the coordinates are formed as
 *   lam_v = (k s_v + h r_v) / (k sum s + h sum r),
 * r the remaining weights: numerator and denominator are smooth and O(1), so their jets are exact.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "jet.h"
#include "native.h"

#define TC_PI 3.14159265358979323846

/* G(t), G'(t), G''(t) for G(t) = int_0^1 dy / (1 + t y^2), 0 <= t <= 1. */
static void g_fun(double t, const double *gy, const double *gw, int ng, double *G) {
    double a = 0, b = 0, c = 0;
    for (int q = 0; q < ng; q++) {
        double y2 = gy[q] * gy[q], r = 1.0 / (1.0 + t * y2), wr = gw[q] * r;
        a += wr;
        b -= wr * y2 * r;
        c += 2.0 * wr * y2 * y2 * r * r;
    }
    G[0] = a, G[1] = b, G[2] = c;
}

/* The divided difference D(U, u) = (G(U) - G(u)) / (U - u) and its partials
 * D, D_U, D_u, D_UU, D_Uu, D_uu. */
static void g_divdiff(double U, double u, const double *gy, const double *gw, int ng, double *D) {
    memset(D, 0, 6 * sizeof(double));
    for (int q = 0; q < ng; q++) {
        double y2 = gy[q] * gy[q], a = 1.0 / (1.0 + U * y2), b = 1.0 / (1.0 + u * y2), w = gw[q];
        double y4 = y2 * y2, y6 = y4 * y2;
        D[0] -= w * y2 * a * b;
        D[1] += w * y4 * a * a * b;
        D[2] += w * y4 * a * b * b;
        D[3] -= 2.0 * w * y6 * a * a * a * b;
        D[4] -= w * y6 * a * a * b * b;
        D[5] -= 2.0 * w * y6 * a * b * b * b;
    }
}

/* G(t) = atan(sqrt t)/sqrt t and its first two derivatives for 0 <= t <= 1: the alternating
 * series below t = 0.1 (24 terms: truncation below 1e-24), the closed form above (G' and G''
 * lose at most a factor 1/t and 1/t^2 of rounding there). */
static const double G_SERIES[24] = {
    1.0,        -1.0 / 3,  1.0 / 5,  -1.0 / 7,  1.0 / 9,  -1.0 / 11, 1.0 / 13, -1.0 / 15,
    1.0 / 17,   -1.0 / 19, 1.0 / 21, -1.0 / 23, 1.0 / 25, -1.0 / 27, 1.0 / 29, -1.0 / 31,
    1.0 / 33,   -1.0 / 35, 1.0 / 37, -1.0 / 39, 1.0 / 41, -1.0 / 43, 1.0 / 45, -1.0 / 47};

static inline void g_closed(double t, double *G) {
    if (t < 0.1) {
        double a0 = 1.0 - t / 3.0, a1 = -1.0 / 3.0, a2 = 0, p = 1.0;  // p = t^(k-2)
        for (int k = 2; k < 24; k++) {
            double c = G_SERIES[k];
            a2 += c * k * (k - 1) * p;
            a1 += c * k * p * t;
            a0 += c * p * t * t;
            p *= t;
        }
        G[0] = a0, G[1] = a1, G[2] = a2;
        return;
    }
    double s = sqrt(t), g = atan(s) / s, q = 1.0 / (1.0 + t), g1 = (q - g) / (2.0 * t);
    G[0] = g, G[1] = g1, G[2] = (-q * q - 3.0 * g1) / (2.0 * t);
}

/* g = theta / (2 |N|) as a jet, from the jets of u = |N|^2 and v = a_j.a_k. */
static jet half_angle_over_norm(jet u, jet v) {
    if (v.v > 0 && u.v <= v.v * v.v) {
        double t = u.v / (v.v * v.v), G[3];
        g_closed(t, G);
        double iv = 1.0 / v.v, tu = iv * iv, tv = -2.0 * t * iv, tuv = -2.0 * tu * iv, tvv = 6.0 * t * iv * iv;
        double h2 = 0.5 * iv;
        double f = G[0] * h2;
        double fu = G[1] * tu * h2;
        double fv = G[1] * tv * h2 - G[0] * h2 * iv;
        double fuu = G[2] * tu * tu * h2;
        double fuv = (G[2] * tu * tv + G[1] * tuv) * h2 - G[1] * tu * h2 * iv;
        double fvv = (G[2] * tv * tv + G[1] * tvv) * h2 - 2.0 * G[1] * tv * h2 * iv + G[0] * iv * iv * iv;
        return j_f2(u, v, f, fu, fv, fuu, fuv, fvv);
    }
    jet s = j_sqrt(u);
    return j_mul(j_atan2(s, v), j_recip(j_scale(s, 2.0)));
}

/* g_e = theta_e / (2 |N_e|) of one edge (j, k) seen from x, as a jet: depends on |N|^2 and
 * a_j.a_k only, so it is shared by the edge's two faces (either orientation). */
static jet edge_phi(const double *aj, const double *ak) {
    double N[3], E[3] = {aj[0] - ak[0], aj[1] - ak[1], aj[2] - ak[2]}, EN[3];
    cross3(aj, ak, N);
    cross3(E, N, EN);
    double E2 = dot3(E, E);
    jet u = {dot3(N, N), {2 * EN[0], 2 * EN[1], 2 * EN[2]},
             {2 * (E2 - E[0] * E[0]), 2 * (E2 - E[1] * E[1]), 2 * (E2 - E[2] * E[2]), -2 * E[0] * E[1],
              -2 * E[0] * E[2], -2 * E[1] * E[2]}};
    jet v = {dot3(aj, ak), {-(aj[0] + ak[0]), -(aj[1] + ak[1]), -(aj[2] + ak[2])}, {2, 2, 2, 0, 0, 0}};
    return half_angle_over_norm(u, v);
}

/* Direct evaluation: weights, gradients and (order 2) Hessians of the three corners, from the
 * edges' jets phi. With F_c = sum_e dphi_e/dx_c E_e, F_v = sum_e phi_e E_e and
 * M_k = sum_e (H phi_e)_k N_e:  N_i . dm/dx_c = sum_e dphi_e/dx_c N_i.N_e + (F_v x N_i)_c and
 * N_i . d2m/dx_c dx_d = N_i . M_cd + (F_c x N_i)_d + (F_d x N_i)_c. */
static void face_direct(const double a[3][3], const double E[3][3], const jet *phi, double two_area, double h,
                        int order, double *w, double g[3][3], double H[3][6]) {
    double N[3][3], m[3] = {0, 0, 0}, Fv[3] = {0, 0, 0}, F[3][3] = {{0}}, M[6][3] = {{0}};
    for (int e = 0; e < 3; e++) {
        cross3(a[(e + 1) % 3], a[(e + 2) % 3], N[e]);
        for (int c = 0; c < 3; c++) {
            m[c] += phi[e].v * N[e][c];
            Fv[c] += phi[e].v * E[e][c];
            for (int d = 0; d < 3; d++) F[d][c] += phi[e].g[d] * E[e][c];
        }
        if (order >= 2)
            for (int k = 0; k < 6; k++)
                for (int c = 0; c < 3; c++) M[k][c] += phi[e].h[k] * N[e][c];
    }
    double idet = 1.0 / (two_area * h), W = 0, gW[3] = {0, 0, 0};
    for (int i = 0; i < 3; i++) {
        w[i] = dot3(N[i], m) * idet;
        W += w[i];
    }
    double FN[3][3][3];  // FN[i][c] = F_c x N_i
    for (int i = 0; i < 3; i++) {
        double FvN[3], nn[3] = {dot3(N[i], N[0]), dot3(N[i], N[1]), dot3(N[i], N[2])};
        cross3(Fv, N[i], FvN);
        for (int c = 0; c < 3; c++) {
            double s = W * N[i][c] + FvN[c];
            for (int e = 0; e < 3; e++) s += phi[e].g[c] * nn[e];
            g[i][c] = s * idet;
            gW[c] += g[i][c];
            cross3(F[c], N[i], FN[i][c]);
        }
    }
    if (order < 2) return;
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 6; k++) {
            int c = JI[k], d = JJ[k];
            H[i][k] = (dot3(N[i], M[k]) + FN[i][c][d] + FN[i][d][c] + gW[d] * N[i][c] + gW[c] * N[i][d]) * idet;
        }
}

/* Near the support plane: the split form with jets. Returns 1 when the point lies on the face. */
static int face_near_plane(const double a[3][3], const double E[3][3], const double *n, double two_area,
                           const double *ell, const double *gram, double tol, const double *gy, const double *gw,
                           int ng, double *w, double g[3][3], double H[3][6], jet *sing, jet *hout) {
    double h = dot3(n, a[0]);
    jet hj = {h, {-n[0], -n[1], -n[2]}, {0, 0, 0, 0, 0, 0}};
    jet h2 = j_mul(hj, hj);
    double P[6];  // 2 (I - n n^T)
    for (int k = 0; k < 6; k++) P[k] = 2.0 * ((JI[k] == JJ[k]) - n[JI[k]] * n[JJ[k]]);
    jet s[3], T[3], S = j_const(0.0);
    double wind_angle = 0.0;
    int inside = 1;
    for (int e = 0; e < 3; e++) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        double Ne[3], En[3], qj[3], qk[3];
        cross3(a[j], a[k], Ne);
        cross3(E[e], n, En);
        for (int c = 0; c < 3; c++) qj[c] = a[j][c] - h * n[c], qk[c] = a[k][c] - h * n[c];
        jet se = {dot3(n, Ne), {En[0], En[1], En[2]}, {0, 0, 0, 0, 0, 0}};
        jet qq = {dot3(qj, qk), {-(qj[0] + qk[0]), -(qj[1] + qk[1]), -(qj[2] + qk[2])}, {P[0], P[1], P[2], P[3], P[4], P[5]}};
        jet d = j_add(qq, h2);
        double l2 = ell[e] * ell[e];
        jet N2 = j_add(j_mul(se, se), j_scale(h2, l2));
        s[e] = se;
        if (se.v < -tol * ell[e]) inside = 0;
        double sig = se.v >= 0 ? 1.0 : -1.0, sabs = sig * se.v + 0.0;  // + 0.0: -0 -> +0 (atan2 tells them apart)
        wind_angle += sig * atan2(sabs, qq.v);
        if (qq.v > 0 && se.v * se.v < 0.64 * qq.v * qq.v && N2.v < d.v * d.v) {
            jet U = j_div(N2, j_mul(d, d)), u = j_div(j_mul(se, se), j_mul(qq, qq));
            double G[3], D[6];
            g_fun(U.v, gy, gw, ng, G);
            g_divdiff(U.v, u.v, gy, gw, ng, D);
            jet gU = j_f1(U, G[0], G[1], G[2]);
            jet Dj = j_f2(U, u, D[0], D[1], D[2], D[3], D[4], D[5]);
            jet qq2 = j_mul(qq, qq), s2 = j_mul(se, se);
            jet poly = j_sub(j_sub(j_scale(qq2, l2), j_scale(j_mul(s2, qq), 2.0)), j_mul(s2, h2));
            jet K = j_sub(j_mul(Dj, j_div(poly, j_mul(j_mul(d, d), j_mul(qq2, qq)))), j_div(gU, j_mul(d, qq)));
            S = j_add(S, j_mul(se, K));
            T[e] = j_div(gU, d);  // theta / |N|
        } else {
            jet sa = j_scale(se, sig);
            sa.v = sabs;
            jet th0 = j_atan2(sa, qq);
            jet Nj = j_sqrt(N2);
            jet Nps = j_add(Nj, sa);
            jet X = j_sub(j_scale(j_div(qq, Nps), l2), sa);
            jet Y = j_add(j_mul(d, qq), j_mul(Nj, sa));
            jet r = j_div(X, Y);  // tan(delta) / h^2
            double A[3];
            atan_over(h * h * r.v, &A[0], &A[1], &A[2]);
            jet dh2 = j_mul(r, j_f1(j_mul(h2, r), A[0], A[1], A[2]));  // delta / h^2
            jet th = j_add(th0, j_mul(h2, dh2));
            T[e] = j_div(th, Nj);
            jet eps = j_scale(j_recip(j_mul(Nj, Nps)), l2);  // epsilon / h^2
            S = j_add(S, j_scale(j_sub(dh2, j_mul(th, eps)), sig));
        }
    }
    if (inside && fabs(h) <= tol) return 1;
    double wind = round(wind_angle / (2.0 * TC_PI)), i4A = 1.0 / (2.0 * two_area);
    for (int i = 0; i < 3; i++) {
        jet B = j_mul(s[i], S);
        for (int e = 0; e < 3; e++) B = j_add(B, j_scale(T[e], gram[3 * i + e]));
        jet wi = j_scale(j_mul(hj, B), i4A);
        sing[i] = j_scale(s[i], 2.0 * TC_PI * wind * i4A);  // the weight's singular part is sing / h
        w[i] = wi.v;
        for (int c = 0; c < 3; c++) g[i][c] = wi.g[c];
        for (int k = 0; k < 6; k++) H[i][k] = wi.h[k];
    }
    *hout = hj;
    return wind != 0.0 ? 2 : 0;
}

/* Whether the foot point of the point lies in the face (within tol): n.(a_j x a_k) >= -tol l_e for
 * every edge. With |h| <= tol, the point is on the face: the near-plane form flags it. */
int tc_in_face_prism(const double a[3][3], const double *n, const double *ell, double tol) {
    for (int e = 0; e < 3; e++) {
        double Ne[3];
        cross3(a[(e + 1) % 3], a[(e + 2) % 3], Ne);
        if (dot3(n, Ne) < -tol * ell[e]) return 0;
    }
    return 1;
}

/* acc[v] (value, gradient, Hessian of w_v) += jet a. */
static inline void acc_add(double *ac, jet a) {
    ac[0] += a.v;
    for (int c = 0; c < 3; c++) ac[1 + c] += a.g[c];
    for (int k = 0; k < 6; k++) ac[4 + k] += a.h[k];
}

/* f = h / |d|^4 (d = p - x, h = n.(p_0 - x)) with its gradient and Hessian in x: f[0], f[1..3], f[4..9]. */
static inline void far_integrand(const double *d, const double *n, double h, double *f) {
    double r2 = dot3(d, d), i2 = 1.0 / r2, i4 = i2 * i2, i6 = i4 * i2, i8 = i4 * i4;
    f[0] = h * i4;
    for (int c = 0; c < 3; c++) f[1 + c] = -n[c] * i4 + 4.0 * h * d[c] * i6;
    for (int k = 0; k < 6; k++) {
        int c = JI[k], e = JJ[k];
        f[4 + k] = -4.0 * (n[c] * d[e] + d[c] * n[e]) * i6 - 4.0 * h * (c == e) * i6 + 24.0 * h * d[c] * d[e] * i8;
    }
}

static inline void acc_out(double acc[3][10], double *w, double g[3][3], double H[3][6]) {
    for (int i = 0; i < 3; i++) {
        w[i] = acc[i][0];
        for (int c = 0; c < 3; c++) g[i][c] = acc[i][1 + c];
        for (int k = 0; k < 6; k++) H[i][k] = acc[i][4 + k];
    }
}

/* Far field: collapsed Gauss rule of h int_T phi_i / |p - x|^4 dA, differentiated under the sign. */
static void face_far(const double *x, const double *n, double h, const double *nodes, const double *coef, int Q,
                     double *w, double g[3][3], double H[3][6]) {
    double acc[3][10];
    memset(acc, 0, sizeof(acc));
    for (int q = 0; q < Q; q++) {
        double d[3] = {nodes[3 * q] - x[0], nodes[3 * q + 1] - x[1], nodes[3 * q + 2] - x[2]}, f[10];
        far_integrand(d, n, h, f);
        for (int i = 0; i < 3; i++) {
            double cq = coef[3 * q + i];
            for (int k = 0; k < 10; k++) acc[i][k] += cq * f[k];
        }
    }
    acc_out(acc, w, g, H);
}

#define THIN_GRADED 64 /* at most this many panels on either side of the foot */

static const double THIN_GL16_X[16] = {0.005299532504175031, 0.0277124884633837, 0.06718439880608412, 0.1222977958224985, 0.19106187779867811, 0.2709916111713863, 0.35919822461037054, 0.4524937450811813, 0.5475062549188188, 0.6408017753896295, 0.7290083888286136, 0.8089381222013219, 0.8777022041775016, 0.9328156011939159, 0.9722875115366163, 0.994700467495825};
static const double THIN_GL16_W[16] = {0.013576229705877088, 0.031126761969323728, 0.0475792558412463, 0.062314485627767036, 0.07479799440828835, 0.08457825969750132, 0.09130170752246182, 0.09472530522753432, 0.09472530522753432, 0.09130170752246182, 0.08457825969750132, 0.07479799440828835, 0.062314485627767036, 0.0475792558412463, 0.031126761969323728, 0.013576229705877088};

static const double THIN_GL8_X[8] = {0.019855071751231912, 0.10166676129318664, 0.23723379504183562,
                                     0.40828267875217505,  0.5917173212478251,  0.7627662049581644,
                                     0.8983332387068135,   0.980144928248768};
static const double THIN_GL8_W[8] = {0.05061426814518814, 0.11119051722668717, 0.15685332293894366,
                                     0.18134189168918097, 0.1813418916891811,  0.15685332293894366,
                                     0.11119051722668717, 0.05061426814518822};

/* Breakpoints bp (returns their count) of [0, 1] graded towards sf: panels of length rho 2^k at
 * rho 2^k from sf (rho: the distance to the point over the segment's length), each no longer than
 * its distance to the point. */
static int graded_breaks(double sf, double rho, double *bp) {
    int n = 0, nl = 0, nr = 0;
    double left[THIN_GRADED], right[THIN_GRADED];
    bp[n++] = 0.0;
    if (rho < 1.0) {
        for (double s = rho; sf - s > 0 && nl < THIN_GRADED; s *= 2) left[nl++] = sf - s;
        for (double s = rho; sf + s < 1 && nr < THIN_GRADED; s *= 2) right[nr++] = sf + s;
        for (int k = nl - 1; k >= 0; --k) bp[n++] = left[k];
        if (sf > 0 && sf < 1) bp[n++] = sf;
        for (int k = 0; k < nr; ++k) bp[n++] = right[k];
    }
    bp[n++] = 1.0;
    return n;
}

/* One segment q0 -> q1 (relative to the point) of the swept form: acc[i] += sum over nodes of
 * (j0 + s j1) (b0_i + s b1_i) f(q(s)) ds, f as far_integrand. */
static void thin_segment(const double *q0, const double *q1, const double *n, double h, double j0, double j1,
                         const double *b0, const double *b1, double acc[3][10]) {
    double D[3] = {q1[0] - q0[0], q1[1] - q0[1], q1[2] - q0[2]}, L2 = dot3(D, D);
    double sf = L2 > 0 ? -dot3(q0, D) / L2 : 0.0;
    sf = sf < 0 ? 0.0 : (sf > 1 ? 1.0 : sf);
    double qf[3] = {q0[0] + sf * D[0], q0[1] + sf * D[1], q0[2] + sf * D[2]};
    double rho = L2 > 0 ? sqrt(dot3(qf, qf) / L2) : 1.0, bp[2 * THIN_GRADED + 3];
    int nb = graded_breaks(sf, rho, bp);
    for (int k = 0; k + 1 < nb; k++) {
        double s0 = bp[k], ds = bp[k + 1] - bp[k];
        for (int q = 0; q < 16; q++) {
            double s = s0 + ds * THIN_GL16_X[q], wq = ds * THIN_GL16_W[q] * (j0 + s * j1), d[3], f[10];
            for (int c = 0; c < 3; c++) d[c] = q0[c] + s * D[c];
            far_integrand(d, n, h, f);
            for (int i = 0; i < 3; i++) {
                double c = wq * (b0[i] + s * b1[i]);
                for (int m = 0; m < 10; m++) acc[i][m] += c * f[m];
            }
        }
    }
}

/* Thin face seen from a few widths: h int_T phi_i / |p - x|^4 dA swept by the polylines
 * A -> C_tau -> B (AB the longest edge, C_tau = F + tau (C - F), F the apex's foot on AB; area
 * element 2A lam s and 2A (1 - lam) (1 - s)), differentiated under the sign. a: corners minus the
 * point, n the unit normal, h = n.a_0; w, g, H in corner order (mvc3d.c takes w alone). Returns 1. */
int tc_thin_mvc(const double a[3][3], const double *n, double h, double two_area, double *w, double g[3][3],
                 double H[3][6]) {
    double L2 = -1.0, acc[3][10];
    int lo = 0;
    for (int i = 0; i < 3; ++i) {
        double E[3] = {a[(i + 2) % 3][0] - a[(i + 1) % 3][0], a[(i + 2) % 3][1] - a[(i + 1) % 3][1],
                       a[(i + 2) % 3][2] - a[(i + 1) % 3][2]};
        double l2 = dot3(E, E);
        if (l2 > L2) L2 = l2, lo = i;
    }
    const int ord[3] = {(lo + 1) % 3, (lo + 2) % 3, lo}; /* A, B, C */
    const double *aA = a[ord[0]], *aB = a[ord[1]], *aC = a[ord[2]];
    double AB[3] = {aB[0] - aA[0], aB[1] - aA[1], aB[2] - aA[2]};
    double CA[3] = {aC[0] - aA[0], aC[1] - aA[1], aC[2] - aA[2]};
    double lam = L2 > 0 ? dot3(CA, AB) / L2 : 0.0;
    lam = lam < 0 ? 0.0 : (lam > 1 ? 1.0 : lam);
    double aF[3] = {aA[0] + lam * AB[0], aA[1] + lam * AB[1], aA[2] + lam * AB[2]};
    double sacc[3][10]; /* in A, B, C order */
    memset(sacc, 0, sizeof(sacc));
    const double bA[3] = {1.0, 0.0, 0.0}, bB[3] = {0.0, 1.0, 0.0};
    for (int m = 0; m < 8; ++m) {
        double tau = THIN_GL8_X[m], wt = THIN_GL8_W[m], part[3][10];
        double aCt[3] = {aF[0] + tau * (aC[0] - aF[0]), aF[1] + tau * (aC[1] - aF[1]), aF[2] + tau * (aC[2] - aF[2])};
        double bC[3] = {(1 - tau) * (1 - lam), (1 - tau) * lam, tau}, b1[3], b2[3];
        for (int i = 0; i < 3; i++) b1[i] = bC[i] - bA[i], b2[i] = bB[i] - bC[i];
        memset(part, 0, sizeof(part));
        thin_segment(aA, aCt, n, h, 0.0, two_area * lam, bA, b1, part);
        thin_segment(aCt, aB, n, h, two_area * (1 - lam), -two_area * (1 - lam), bC, b2, part);
        for (int i = 0; i < 3; i++)
            for (int k = 0; k < 10; k++) sacc[i][k] += wt * part[i][k];
    }
    for (int i = 0; i < 3; i++)
        for (int k = 0; k < 10; k++) acc[ord[i]][k] = sacc[i][k];
    acc_out(acc, w, g, H);
    return 1;
}

/* The jet of vertex v's accumulated weight (acc holds value, gradient and Hessian: 10 per vertex). */
static inline jet acc_jet(const double *ac) {
    jet r = {ac[0], {ac[1], ac[2], ac[3]}, {ac[4], ac[5], ac[6], ac[7], ac[8], ac[9]}};
    return r;
}

/* Writes the coordinate jet lam of vertex v at point p: L (n, V), G (n, V, 3), H (n, V, 3, 3). */
static inline void store_lam(jet lam, long p, long V, long v, int order, double *L, double *G, double *H) {
    L[p * V + v] = lam.v;
    for (int c = 0; c < 3; c++) G[(p * V + v) * 3 + c] = lam.g[c];
    if (order < 2) return;
    double *Hp = H + (p * V + v) * 9;
    for (int k = 0; k < 6; k++) Hp[3 * JI[k] + JJ[k]] = Hp[3 * JJ[k] + JI[k]] = lam.h[k];
}

/* Mean value coordinates and their derivatives at n points.
 * P (V, 3) vertices; tri (T, 3) int32 corners; E (T, 3, 3) edge vectors p_{e+1} - p_{e+2};
 * nrm (T, 3) unit normals; two_area (T); ell (T, 3) edge lengths; gram (T, 3, 3) E_i.E_e;
 * longest (T); far_nodes (T, Q, 3), far_coef (T, Q, 3); gl_y, gl_w (ng) Gauss-Legendre on [0, 1];
 * fe (T, 3) int32 index of the unique edge opposite each corner (NE edges); X (n, 3).
 * Writes L (n, V), G (n, V, 3) and, for order 2, H (n, V, 3, 3). on[p] = 1 for points on the cage
 * (rows: the barycentric interpolant of a face holding the point, its gradient in the face's
 * plane, Hessian 0; Lagrange at a vertex, derivatives 0), 2 where the total weight vanishes. */
/* One cage of tc_mvcd3d's batch; returns 1 when its scratch could not be allocated. */
static int mvcd3d_one(const double *P, long V, const int *tri, long T, const int *fe, long NE, const double *E,
                      const double *nrm, const double *two_area, const double *ell, const double *gram,
                      const double *longest, const double *far_nodes, const double *far_coef, long Q, double far_c,
                      double near_c, const double *gl_y, const double *gl_w, int ng, const double *X, long n,
                      double tol, int order, int nthreads, double *L, double *G, double *H, unsigned char *on) {
    double centre[3];
    const double far2 = tc_far_centre(P, V, 3, 1, 3, centre);
    unsigned char *thin = (unsigned char *)malloc((size_t)(T > 0 ? T : 1));
    if (!thin) return 1;
    for (long t = 0; t < T; t++) thin[t] = two_area[t] > 0 && longest[t] * longest[t] > TC_THIN_ASPECT * two_area[t];
    int failed = 0; /* a thread could not allocate its scratch */
#pragma omp parallel num_threads(nthreads)
    {
        double *acc = (double *)malloc(sizeof(double) * 10 * (size_t)V);
        double *av = (double *)malloc(sizeof(double) * 4 * (size_t)V);  // p_v - x and |p_v - x|
        jet *ephi = (jet *)malloc(sizeof(jet) * (size_t)(NE > 0 ? NE : 1)); // edge jets, computed on demand
        long *stamp = (long *)malloc(sizeof(long) * (size_t)(NE > 0 ? NE : 1));
        if (!acc || !av || !ephi || !stamp) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp barrier
        if (failed) goto done; /* (every thread: none enters the worksharing loop) */
        for (long e = 0; e < NE; e++) stamp[e] = -1;
#pragma omp for schedule(dynamic, 16)
        for (long p = 0; p < n; p++) {
            const double *x = X + 3 * p;
            memset(acc, 0, sizeof(double) * 10 * V);
            for (long v = 0; v < V; v++) {
                double *ap = av + 4 * v;
                for (int c = 0; c < 3; c++) ap[c] = P[3 * v + c] - x[c];
                ap[3] = sqrt(dot3(ap, ap));
            }
            int flag = 0, sidx[3] = {0, 0, 0};
            long sface = -1, on_face = -1, on_vertex = -1;  // the nearest face whose foot point the point sees inside (see above)
            jet ssing[3], shj = j_const(0.0);
            for (long t = 0; t < T && !flag; t++) {
                const int *ti = tri + 3 * t;
                double a[3][3], R[3], Et[3][3], w[3], g[3][3], Hh[3][6];
                for (int i = 0; i < 3; i++) {
                    const double *ap = av + 4 * ti[i];
                    for (int c = 0; c < 3; c++) a[i][c] = ap[c], Et[i][c] = E[9 * t + 3 * i + c];
                    R[i] = ap[3];
                }
                double minR = fmin(R[0], fmin(R[1], R[2]));
                if (minR <= tol) {
                    flag = 1, on_face = t, on_vertex = ti[R[0] <= tol ? 0 : (R[1] <= tol ? 1 : 2)];
                    break;
                }
                const double *nt = nrm + 3 * t;
                double h = dot3(nt, a[0]);
                if (thin[t] && tc_thin_face((const double(*)[3])a, two_area[t]) &&
                    (fabs(h) > tol || !tc_in_face_prism(a, nt, ell + 3 * t, tol))) {
                    tc_thin_mvc((const double(*)[3])a, nt, h, two_area[t], w, g, Hh);
                } else if (longest[t] <= far_c * minR) {
                    face_far(x, nt, h, far_nodes + 3 * Q * t, far_coef + 3 * Q * t, (int)Q, w, g, Hh);
                } else if (fabs(h) < near_c * minR) {
                    jet sg[3], hj;
                    int r = face_near_plane(a, Et, nt, two_area[t], ell + 3 * t, gram + 9 * t, tol, gl_y, gl_w, ng, w,
                                            g, Hh, sg, &hj);
                    if (r == 1) {
                        flag = 1, on_face = t;
                        break;
                    }
                    if (r == 2) {  // keep the nearest face's singular part apart, fold any other back in
                        if (sface >= 0 && fabs(hj.v) < fabs(shj.v)) {
                            for (int i = 0; i < 3; i++) acc_add(acc + 10 * sidx[i], j_div(ssing[i], shj));
                            sface = -1;
                        }
                        if (sface < 0) {
                            sface = t, shj = hj;
                            for (int i = 0; i < 3; i++) ssing[i] = sg[i], sidx[i] = ti[i];
                        } else {
                            for (int i = 0; i < 3; i++) acc_add(acc + 10 * ti[i], j_div(sg[i], hj));
                        }
                    }
                } else {
                    jet phi[3];
                    for (int e = 0; e < 3; e++) {
                        long k = fe[3 * t + e];
                        if (stamp[k] != p) {
                            ephi[k] = edge_phi(a[(e + 1) % 3], a[(e + 2) % 3]);
                            stamp[k] = p;
                        }
                        phi[e] = ephi[k];
                    }
                    face_direct(a, Et, phi, two_area[t], h, order, w, g, Hh);
                }
                for (int i = 0; i < 3; i++) {
                    double *ac = acc + 10 * ti[i];
                    ac[0] += w[i];
                    for (int c = 0; c < 3; c++) ac[1 + c] += g[i][c];
                    if (order >= 2)
                        for (int k = 0; k < 6; k++) ac[4 + k] += Hh[i][k];
                }
            }
            on[p] = (unsigned char)flag;
            if (flag && on_vertex < 0) {  // the largest face holding the point (the torch kernel's choice;
                                          // areas within TC_AREA_TIE of each other: the first)
                for (long t = on_face + 1; t < T; t++) {
                    const int *ti = tri + 3 * t;
                    double a[3][3], minR = INFINITY;
                    for (int i = 0; i < 3; i++) {
                        for (int c = 0; c < 3; c++) a[i][c] = av[4 * ti[i] + c];
                        minR = fmin(minR, av[4 * ti[i] + 3]);
                    }
                    double h = fabs(dot3(nrm + 3 * t, a[0]));
                    if (two_area[t] > two_area[on_face] * (1 + TC_AREA_TIE) && !(longest[t] <= far_c * minR) &&
                        h <= tol && h < near_c * minR && tc_in_face_prism(a, nrm + 3 * t, ell + 3 * t, tol))
                        on_face = t;
                }
            }
            if (flag) {  // on the cage: the interpolant's values and (one-sided, tangential) derivatives
                memset(L + p * V, 0, sizeof(double) * V);
                memset(G + p * V * 3, 0, sizeof(double) * V * 3);
                if (order >= 2) memset(H + p * V * 9, 0, sizeof(double) * V * 9);
                if (on_vertex >= 0) {
                    L[p * V + on_vertex] = 1.0;
                    continue;
                }
                const int *ti = tri + 3 * on_face;
                const double *nt = nrm + 3 * on_face;
                for (int i = 0; i < 3; i++) {  // barycentric b_i = n.(a_j x a_k) / (2 area), grad (E_i x n) / (2 area)
                    const double *aj = av + 4 * ti[(i + 1) % 3], *ak = av + 4 * ti[(i + 2) % 3];
                    double Ne[3], En[3];
                    cross3(aj, ak, Ne);
                    cross3(E + 9 * on_face + 3 * i, nt, En);
                    L[p * V + ti[i]] = dot3(nt, Ne) / two_area[on_face];
                    for (int c = 0; c < 3; c++) G[(p * V + ti[i]) * 3 + c] = En[c] / two_area[on_face];
                }
                continue;
            }
            if (sface >= 0) {  // lam_v = (k s_v + h r_v) / (k sum s + h sum r)
                jet R = j_const(0.0), den;
                for (long v = 0; v < V; v++) R = j_add(R, acc_jet(acc + 10 * v));
                den = j_mul(shj, R);
                for (int i = 0; i < 3; i++) den = j_add(den, ssing[i]);
                if (!(den.v != 0.0) || !isfinite(den.v)) {
                    on[p] = 2;
                    continue;
                }
                jet iden = j_recip(den);
                for (long v = 0; v < V; v++) {
                    jet num = j_mul(shj, acc_jet(acc + 10 * v));
                    for (int i = 0; i < 3; i++)
                        if (sidx[i] == v) num = j_add(num, ssing[i]);
                    store_lam(j_mul(num, iden), p, V, v, order, L, G, H);
                }
                continue;
            }
            double yc[3], y2 = 0.0;
            for (int c = 0; c < 3; c++) {
                yc[c] = x[c] - centre[c];
                y2 += yc[c] * yc[c];
            }
            if (y2 > far2) {
                /* Far from the cage the sum of the weights cancels: normalise by their first moment
                 * M = (sum_v w_v (P_v - c)) . y / |y|^2, y = x - c (tc_mv_total), as a jet. */
                jet S[3] = {j_const(0.0), j_const(0.0), j_const(0.0)}, num = j_const(0.0), den = j_const(y2);
                for (long v = 0; v < V; v++) {
                    jet wv = acc_jet(acc + 10 * v);
                    for (int k = 0; k < 3; k++) S[k] = j_add(S[k], j_scale(wv, P[3 * v + k] - centre[k]));
                }
                for (int k = 0; k < 3; k++) {
                    jet yk = j_const(yc[k]);
                    yk.g[k] = 1.0;
                    num = j_add(num, j_mul(S[k], yk));
                    den.g[k] = 2.0 * yc[k];
                    den.h[k] = 2.0;
                }
                jet M = j_div(num, den);
                if (!(M.v != 0.0) || !isfinite(M.v)) {
                    on[p] = 2;
                    continue;
                }
                jet iM = j_recip(M);
                for (long v = 0; v < V; v++) store_lam(j_mul(acc_jet(acc + 10 * v), iM), p, V, v, order, L, G, H);
                continue;
            }
            double W = 0, gW[3] = {0, 0, 0}, HW[6] = {0, 0, 0, 0, 0, 0};
            for (long v = 0; v < V; v++) {
                W += acc[10 * v];
                for (int c = 0; c < 3; c++) gW[c] += acc[10 * v + 1 + c];
                for (int k = 0; k < 6; k++) HW[k] += acc[10 * v + 4 + k];
            }
            if (!(W != 0.0) || !isfinite(W)) {
                on[p] = 2;
                continue;
            }
            double iW = 1.0 / W;
            for (long v = 0; v < V; v++) {
                const double *ac = acc + 10 * v;
                double lam = ac[0] * iW, gl[3];
                L[p * V + v] = lam;
                for (int c = 0; c < 3; c++) {
                    gl[c] = (ac[1 + c] - lam * gW[c]) * iW;
                    G[(p * V + v) * 3 + c] = gl[c];
                }
                if (order < 2) continue;
                double *Hp = H + (p * V + v) * 9;
                for (int k = 0; k < 6; k++) {
                    int c = JI[k], d = JJ[k];
                    double val = (ac[4 + k] - lam * HW[k] - gl[c] * gW[d] - gW[c] * gl[d]) * iW;
                    Hp[3 * c + d] = val;
                    Hp[3 * d + c] = val;
                }
            }
        }
    done:
        free(acc);
        free(av);
        free(ephi);
        free(stamp);
    }
    free(thin);
    return failed;
}

/* Mean value coordinates with their gradients and (order 2) Hessians for a batch of B cages with one
 * topology: the geometric tables carry a leading batch axis (P (B, V, 3), E (B, T, 3, 3), nrm, two_area,
 * ell, gram, longest, far_nodes, far_coef, tol (B,)), the topology ones (tri, fe) are shared; points X
 * (XB, n, 3) with XB = 1 (shared by every cage) or B; outputs L (B, n, V), G (B, n, V, 3), H (B, n, V,
 * 3, 3) or NULL, on (B, n). The cages one after the other, each parallel over its points. A failed
 * allocation sets every flag to 3 (and L to NaN; the glue raises MemoryError). XB must be 1 or B (the
 * glue checks). */
void tc_mvcd3d(long B, const double *P, long V, const int *tri, long T, const int *fe, long NE, const double *E,
               const double *nrm, const double *two_area, const double *ell, const double *gram,
               const double *longest, const double *far_nodes, const double *far_coef, long Q, double far_c,
               double near_c, const double *gl_y, const double *gl_w, int ng, const double *X, long XB, long n,
               const double *tol, int order, int nthreads, double *L, double *G, double *H, unsigned char *on) {
    int failed = 0;
    for (long b = 0; b < B && !failed; ++b) {
        const long t3 = b * T * 3, t9 = b * T * 9, tq = b * T * Q * 3, nv = b * n * V;
        failed = mvcd3d_one(P + b * V * 3, V, tri, T, fe, NE, E + t9, nrm + t3, two_area + b * T, ell + t3, gram + t9,
                            longest + b * T, far_nodes + tq, far_coef + tq, Q, far_c, near_c, gl_y, gl_w, ng,
                            X + (XB > 1 ? b : 0) * n * 3, n, tol[b], order, nthreads, L + nv, G + 3 * nv,
                            H ? H + 9 * nv : NULL, on + b * n);
    }
    if (failed) {
        for (long k = 0; k < B * n * V; ++k) L[k] = NAN;
        memset(on, 3, (size_t)(B * n)); /* (WORKSPACE_FAILED: the glue raises MemoryError) */
    }
}
