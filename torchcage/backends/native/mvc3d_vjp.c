/*
 * Vector-Jacobian products of 3D mean value coordinates with respect to the query points and the
 * rest cage's vertices at once (float64): the hand-derived reverse mode of the direct vector form,
 * the same formulas and the same "regular point" test as torchcage/families/mean_value/vjp3d.py (its
 * docstring gives the derivation) and as tc_mvc_face_direct / tc_mvc_face_adjoint (native.h), which
 * the near-plane kernel (mvc3d_vjp_near.c) takes one point at a time. Here VJP_LANES points go side
 * by side (vjp_block: each face's forward and reverse pass vectorised across the points, libmvec's
 * atan2); OpenMP over blocks; each thread sums its vertex gradients lane by lane in its own buffer,
 * added up at the end.
 *
 * P (V, 3) vertices; tri (T, 3) int32 corners; X (n, 3) points; G (n, V) the cotangent dL/dlam.
 * Outputs: GX (n, 3) dL/dx (zero rows for points that are not regular), GP (V, 3) dL/dP summed
 * over the regular points, reg (n,) 1 where the point is regular. A point is regular when, for
 * every face, |h| >= near_c * min_i |a_i| (h the distance to the face's plane), min_i |a_i| > tol,
 * the face is not seen below 1/far_always of its longest edge, no thin face is seen from a few
 * widths (tc_thin_face: the direct form cancels there), and the face weights do not cancel
 * (sum_T |sum_i w_i| <= cancel_c |W|). The caller treats the other points with the torch kernel.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector atan2 (libmvec) in the lane loops below. */
__attribute__((simd("notinbranch"))) double atan2(double, double);
#endif

#ifndef VJP_LANES
#define VJP_LANES 4 /* points side by side (one AVX2 register of doubles; 8 measured slower) */
#endif
#define VL VJP_LANES

/* A face's scratch, field by field, each field VL lanes wide: the layout of native.h's TC_FA_*
 * (a_i = p_i - x, N_e, |N_e|, d_e, theta_e, g_e, m, det, w_i). */
#define FS(field) (s + (size_t)(field) * VL)

/* dot and cross products of (x, y, z) triples given as three expressions each (the operation
 * order of native.h's dot3 and cross3, so that the lanes round as the one-point code does) */
#define DOT(ax, ay, az, bx, by, bz) ((ax) * (bx) + (ay) * (by) + (az) * (bz))

/* The block's forward pass: face scratch S (T faces x TC_FA_SIZE fields x VL lanes), raw weights
 * Wv (V x VL), per lane the sum of |sum_i w_i| (asum) and whether some face is not regular (bad). */
static void vjp_forward(const double *P, const int *tri, long T, const double *two_area, const double *longest,
                        int any_thin, const double *x0, const double *x1, const double *x2, double tol, double near_c,
                        double far_always, double *S, double *Wv, double *asum, double *bad) {
    for (long f = 0; f < T; ++f) {
        const int *t = tri + 3 * f;
        const double *q0 = P + 3 * t[0], *q1 = P + 3 * t[1], *q2 = P + 3 * t[2];
        const double ta = two_area[f], lo = longest[f];
        double *s = S + (size_t)f * TC_FA_SIZE * VL, *W0 = Wv + VL * t[0], *W1 = Wv + VL * t[1], *W2 = Wv + VL * t[2];
        double *A = FS(TC_FA_A), *N = FS(TC_FA_N), *NN = FS(TC_FA_NN), *D = FS(TC_FA_D), *TH = FS(TC_FA_TH);
        double *GE = FS(TC_FA_G), *M = FS(TC_FA_M), *DET = FS(TC_FA_DET), *W = FS(TC_FA_W);
#pragma omp simd
        for (int l = 0; l < VL; ++l) {
            double a0x = q0[0] - x0[l], a0y = q0[1] - x1[l], a0z = q0[2] - x2[l];
            double a1x = q1[0] - x0[l], a1y = q1[1] - x1[l], a1z = q1[2] - x2[l];
            double a2x = q2[0] - x0[l], a2y = q2[1] - x1[l], a2z = q2[2] - x2[l];
            double R0 = sqrt(DOT(a0x, a0y, a0z, a0x, a0y, a0z)), R1 = sqrt(DOT(a1x, a1y, a1z, a1x, a1y, a1z));
            double R2 = sqrt(DOT(a2x, a2y, a2z, a2x, a2y, a2z));
            double rmin = R1 < R0 ? R1 : R0;
            rmin = R2 < rmin ? R2 : rmin;
            /* N_e = a_j x a_k, (j, k) = (1, 2), (2, 0), (0, 1) */
            double n0x = a1y * a2z - a1z * a2y, n0y = a1z * a2x - a1x * a2z, n0z = a1x * a2y - a1y * a2x;
            double n1x = a2y * a0z - a2z * a0y, n1y = a2z * a0x - a2x * a0z, n1z = a2x * a0y - a2y * a0x;
            double n2x = a0y * a1z - a0z * a1y, n2y = a0z * a1x - a0x * a1z, n2z = a0x * a1y - a0y * a1x;
            double nn0 = sqrt(DOT(n0x, n0y, n0z, n0x, n0y, n0z)), d0 = DOT(a1x, a1y, a1z, a2x, a2y, a2z);
            double nn1 = sqrt(DOT(n1x, n1y, n1z, n1x, n1y, n1z)), d1 = DOT(a2x, a2y, a2z, a0x, a0y, a0z);
            double nn2 = sqrt(DOT(n2x, n2y, n2z, n2x, n2y, n2z)), d2 = DOT(a0x, a0y, a0z, a1x, a1y, a1z);
            double th0 = atan2(nn0, d0), th1 = atan2(nn1, d1), th2 = atan2(nn2, d2);
            double g0 = th0 / (2.0 * (nn0 > 0 ? nn0 : 1.0)), g1 = th1 / (2.0 * (nn1 > 0 ? nn1 : 1.0));
            double g2 = th2 / (2.0 * (nn2 > 0 ? nn2 : 1.0));
            double mx = 0.0, my = 0.0, mz = 0.0;
            mx += g0 * n0x, my += g0 * n0y, mz += g0 * n0z;
            mx += g1 * n1x, my += g1 * n1y, mz += g1 * n1z;
            mx += g2 * n2x, my += g2 * n2y, mz += g2 * n2z;
            double det = DOT(a0x, a0y, a0z, n0x, n0y, n0z);
            int ok = fabs(det) >= near_c * rmin * ta && rmin > tol && lo * far_always >= rmin;
            bad[l] = ok ? bad[l] : 1.0;
            double w0 = DOT(n0x, n0y, n0z, mx, my, mz) / det, w1 = DOT(n1x, n1y, n1z, mx, my, mz) / det;
            double w2 = DOT(n2x, n2y, n2z, mx, my, mz) / det, fsum = 0.0;
            fsum += w0, fsum += w1, fsum += w2;
            asum[l] += fabs(fsum);
            W0[l] += w0, W1[l] += w1, W2[l] += w2;
            A[0 * VL + l] = a0x, A[1 * VL + l] = a0y, A[2 * VL + l] = a0z, A[3 * VL + l] = a1x, A[4 * VL + l] = a1y;
            A[5 * VL + l] = a1z, A[6 * VL + l] = a2x, A[7 * VL + l] = a2y, A[8 * VL + l] = a2z;
            N[0 * VL + l] = n0x, N[1 * VL + l] = n0y, N[2 * VL + l] = n0z, N[3 * VL + l] = n1x, N[4 * VL + l] = n1y;
            N[5 * VL + l] = n1z, N[6 * VL + l] = n2x, N[7 * VL + l] = n2y, N[8 * VL + l] = n2z;
            NN[l] = nn0, NN[VL + l] = nn1, NN[2 * VL + l] = nn2, D[l] = d0, D[VL + l] = d1, D[2 * VL + l] = d2;
            TH[l] = th0, TH[VL + l] = th1, TH[2 * VL + l] = th2, GE[l] = g0, GE[VL + l] = g1, GE[2 * VL + l] = g2;
            M[l] = mx, M[VL + l] = my, M[2 * VL + l] = mz, DET[l] = det;
            W[l] = w0, W[VL + l] = w1, W[2 * VL + l] = w2;
        }
        if (any_thin && lo * lo > TC_THIN_ASPECT * ta) /* a thin face seen from a few widths: not regular */
            for (int l = 0; l < VL; ++l) {
                double a[3][3];
                for (int i = 0; i < 9; ++i) a[i / 3][i % 3] = A[i * VL + l];
                if (bad[l] == 0.0 && tc_thin_face((const double(*)[3])a, ta)) bad[l] = 1.0;
            }
    }
}

/* The block's reverse pass over the faces (tc_mvc_face_adjoint lane by lane, written out so that
 * the lane loop vectorises; the same operations in the same order): wbar (V x VL) the
 * cotangent of the raw weights; adds dL/dp to gpl ((V x 3) x VL, masked by ok) and -sum_i abar_i to
 * the lanes' gx0, gx1, gx2. */
static void vjp_reverse(const int *tri, long T, const double *S, const double *wbar, const double *ok, double *gpl,
                        double *gx0, double *gx1, double *gx2) {
    for (long f = 0; f < T; ++f) {
        const int *t = tri + 3 * f;
        const double *s = S + (size_t)f * TC_FA_SIZE * VL;
        const double *A = FS(TC_FA_A), *N = FS(TC_FA_N), *NN = FS(TC_FA_NN), *D = FS(TC_FA_D), *TH = FS(TC_FA_TH);
        const double *GE = FS(TC_FA_G), *M = FS(TC_FA_M), *DET = FS(TC_FA_DET), *W = FS(TC_FA_W);
        const double *B0 = wbar + VL * t[0], *B1 = wbar + VL * t[1], *B2 = wbar + VL * t[2];
        double *P0 = gpl + 3 * VL * t[0], *P1 = gpl + 3 * VL * t[1], *P2 = gpl + 3 * VL * t[2];
#pragma omp simd
        for (int l = 0; l < VL; ++l) {
            double a0x = A[0 * VL + l], a0y = A[1 * VL + l], a0z = A[2 * VL + l];
            double a1x = A[3 * VL + l], a1y = A[4 * VL + l], a1z = A[5 * VL + l];
            double a2x = A[6 * VL + l], a2y = A[7 * VL + l], a2z = A[8 * VL + l];
            double n0x = N[0 * VL + l], n0y = N[1 * VL + l], n0z = N[2 * VL + l];
            double n1x = N[3 * VL + l], n1y = N[4 * VL + l], n1z = N[5 * VL + l];
            double n2x = N[6 * VL + l], n2y = N[7 * VL + l], n2z = N[8 * VL + l];
            double mx = M[l], my = M[VL + l], mz = M[2 * VL + l];
            const double inv_det = 1.0 / DET[l];
            double wb0 = B0[l] * inv_det, wb1 = B1[l] * inv_det, wb2 = B2[l] * inv_det, det_bar = 0.0;
            double mbx = 0.0, mby = 0.0, mbz = 0.0;
            det_bar -= wb0 * W[0 * VL + l];
            mbx += wb0 * n0x, mby += wb0 * n0y, mbz += wb0 * n0z;
            double nb0x = wb0 * mx, nb0y = wb0 * my, nb0z = wb0 * mz;
            det_bar -= wb1 * W[1 * VL + l];
            mbx += wb1 * n1x, mby += wb1 * n1y, mbz += wb1 * n1z;
            double nb1x = wb1 * mx, nb1y = wb1 * my, nb1z = wb1 * mz;
            det_bar -= wb2 * W[2 * VL + l];
            mbx += wb2 * n2x, mby += wb2 * n2y, mbz += wb2 * n2z;
            double nb2x = wb2 * mx, nb2y = wb2 * my, nb2z = wb2 * mz;
            double ab0x = det_bar * n0x, ab0y = det_bar * n0y, ab0z = det_bar * n0z;
            double ab1x = det_bar * n1x, ab1y = det_bar * n1y, ab1z = det_bar * n1z;
            double ab2x = det_bar * n2x, ab2y = det_bar * n2y, ab2z = det_bar * n2z;
            {
                double nn = NN[0 * VL + l], d = D[0 * VL + l], safe_nn = nn > 0 ? nn : 1.0;
                double gbar = DOT(n0x, n0y, n0z, mbx, mby, mbz), th_bar = gbar / (2.0 * safe_nn);
                double r2 = nn * nn + d * d, safe_r2 = r2 > 0 ? r2 : 1.0;
                double n_bar = -gbar * TH[0 * VL + l] / (2.0 * safe_nn * safe_nn) + th_bar * d / safe_r2;
                double d_bar = -th_bar * nn / safe_r2, coef = n_bar / safe_nn, ge = GE[0 * VL + l];
                nb0x += ge * mbx + coef * n0x, nb0y += ge * mby + coef * n0y, nb0z += ge * mbz + coef * n0z;
                double cjx = a2y * nb0z - a2z * nb0y, cjy = a2z * nb0x - a2x * nb0z;
                double cjz = a2x * nb0y - a2y * nb0x;
                double ckx = nb0y * a1z - nb0z * a1y, cky = nb0z * a1x - nb0x * a1z;
                double ckz = nb0x * a1y - nb0y * a1x;
                ab1x += d_bar * a2x + cjx, ab1y += d_bar * a2y + cjy, ab1z += d_bar * a2z + cjz;
                ab2x += d_bar * a1x + ckx, ab2y += d_bar * a1y + cky, ab2z += d_bar * a1z + ckz;
            }
            {
                double nn = NN[1 * VL + l], d = D[1 * VL + l], safe_nn = nn > 0 ? nn : 1.0;
                double gbar = DOT(n1x, n1y, n1z, mbx, mby, mbz), th_bar = gbar / (2.0 * safe_nn);
                double r2 = nn * nn + d * d, safe_r2 = r2 > 0 ? r2 : 1.0;
                double n_bar = -gbar * TH[1 * VL + l] / (2.0 * safe_nn * safe_nn) + th_bar * d / safe_r2;
                double d_bar = -th_bar * nn / safe_r2, coef = n_bar / safe_nn, ge = GE[1 * VL + l];
                nb1x += ge * mbx + coef * n1x, nb1y += ge * mby + coef * n1y, nb1z += ge * mbz + coef * n1z;
                double cjx = a0y * nb1z - a0z * nb1y, cjy = a0z * nb1x - a0x * nb1z;
                double cjz = a0x * nb1y - a0y * nb1x;
                double ckx = nb1y * a2z - nb1z * a2y, cky = nb1z * a2x - nb1x * a2z;
                double ckz = nb1x * a2y - nb1y * a2x;
                ab2x += d_bar * a0x + cjx, ab2y += d_bar * a0y + cjy, ab2z += d_bar * a0z + cjz;
                ab0x += d_bar * a2x + ckx, ab0y += d_bar * a2y + cky, ab0z += d_bar * a2z + ckz;
            }
            {
                double nn = NN[2 * VL + l], d = D[2 * VL + l], safe_nn = nn > 0 ? nn : 1.0;
                double gbar = DOT(n2x, n2y, n2z, mbx, mby, mbz), th_bar = gbar / (2.0 * safe_nn);
                double r2 = nn * nn + d * d, safe_r2 = r2 > 0 ? r2 : 1.0;
                double n_bar = -gbar * TH[2 * VL + l] / (2.0 * safe_nn * safe_nn) + th_bar * d / safe_r2;
                double d_bar = -th_bar * nn / safe_r2, coef = n_bar / safe_nn, ge = GE[2 * VL + l];
                nb2x += ge * mbx + coef * n2x, nb2y += ge * mby + coef * n2y, nb2z += ge * mbz + coef * n2z;
                double cjx = a1y * nb2z - a1z * nb2y, cjy = a1z * nb2x - a1x * nb2z;
                double cjz = a1x * nb2y - a1y * nb2x;
                double ckx = nb2y * a0z - nb2z * a0y, cky = nb2z * a0x - nb2x * a0z;
                double ckz = nb2x * a0y - nb2y * a0x;
                ab0x += d_bar * a1x + cjx, ab0y += d_bar * a1y + cjy, ab0z += d_bar * a1z + cjz;
                ab1x += d_bar * a0x + ckx, ab1y += d_bar * a0y + cky, ab1z += d_bar * a0z + ckz;
            }
            const int on = ok[l] != 0.0; /* (a lane that is not regular may hold inf or NaN: never added) */
            P0[l] += on ? ab0x : 0.0, P0[VL + l] += on ? ab0y : 0.0, P0[2 * VL + l] += on ? ab0z : 0.0;
            P1[l] += on ? ab1x : 0.0, P1[VL + l] += on ? ab1y : 0.0, P1[2 * VL + l] += on ? ab1z : 0.0;
            P2[l] += on ? ab2x : 0.0, P2[VL + l] += on ? ab2y : 0.0, P2[2 * VL + l] += on ? ab2z : 0.0;
            gx0[l] -= ab0x, gx1[l] -= ab0y, gx2[l] -= ab0z;
            gx0[l] -= ab1x, gx1[l] -= ab1y, gx2[l] -= ab1z;
            gx0[l] -= ab2x, gx1[l] -= ab2y, gx2[l] -= ab2z;
        }
    }
}

/* The points p0 .. p0 + cnt - 1 (cnt <= VL; lanes past cnt repeat the last point and are never
 * regular): GX, reg for them, their vertex gradients added to gpl. ws: vjp_workspace doubles. */
static void vjp_block(const double *P, long V, const int *tri, long T, const double *two_area, const double *longest,
                      int any_thin, const double *X, const double *G, long p0, int cnt, double tol, double near_c,
                      double cancel_c, double far_always, double *ws, double *gpl, double *GX, unsigned char *reg) {
    double *S = ws, *Wv = S + (size_t)TC_FA_SIZE * T * VL, *wbar = Wv + (size_t)V * VL;
    double x0[VL], x1[VL], x2[VL], bad[VL], asum[VL], tot[VL], ok[VL], gx0[VL], gx1[VL], gx2[VL];
    long row[VL];
    for (int l = 0; l < VL; ++l) {
        row[l] = p0 + (l < cnt ? l : cnt - 1);
        x0[l] = X[3 * row[l]], x1[l] = X[3 * row[l] + 1], x2[l] = X[3 * row[l] + 2];
        bad[l] = l < cnt ? 0.0 : 1.0, asum[l] = tot[l] = gx0[l] = gx1[l] = gx2[l] = 0.0;
    }
    memset(Wv, 0, sizeof(double) * (size_t)V * VL);
    vjp_forward(P, tri, T, two_area, longest, any_thin, x0, x1, x2, tol, near_c, far_always, S, Wv, asum, bad);
    for (long v = 0; v < V; ++v)
#pragma omp simd
        for (int l = 0; l < VL; ++l) tot[l] += Wv[VL * v + l];
    int any = 0;
    for (int l = 0; l < VL; ++l) {
        ok[l] = bad[l] == 0.0 && asum[l] <= cancel_c * fabs(tot[l]) && tot[l] != 0.0 ? 1.0 : 0.0;
        any |= ok[l] != 0.0;
        if (ok[l] == 0.0) continue;
        const double *g = G + row[l] * V;
        double sg = 0.0;
        for (long v = 0; v < V; ++v) sg += g[v] * Wv[VL * v + l];
        sg /= tot[l];
        for (long v = 0; v < V; ++v) wbar[VL * v + l] = (g[v] - sg) / tot[l];
    }
    if (any) {
        for (int l = 0; l < VL; ++l) /* (lanes that are not regular: any finite cotangent) */
            if (ok[l] == 0.0)
                for (long v = 0; v < V; ++v) wbar[VL * v + l] = 0.0;
        vjp_reverse(tri, T, S, wbar, ok, gpl, gx0, gx1, gx2);
    }
    for (int l = 0; l < cnt; ++l) {
        double *gx = GX + 3 * (p0 + l);
        gx[0] = ok[l] != 0.0 ? gx0[l] : 0.0, gx[1] = ok[l] != 0.0 ? gx1[l] : 0.0, gx[2] = ok[l] != 0.0 ? gx2[l] : 0.0;
        reg[p0 + l] = ok[l] != 0.0;
    }
}

/* tc_mvc3d_vjp_batch's work for B cages with one topology (P (B, V, 3), X (B, n, 3), G (B, n, V),
 * tol (B,); outputs GX (B, n, 3), GP (B, V, 3), reg (B, n)): element by element the same blocks. */
static void vjp_run(long B, const double *P, long V, const int *tri, long T, const double *X, long n, const double *G,
                    const double *tol, double near_c, double cancel_c, double far_always, int nthreads, double *GX,
                    double *GP, unsigned char *reg) {
    memset(GP, 0, sizeof(double) * 3 * (size_t)(B * V));
    /* per element: twice the faces' areas, their longest edges, whether one is thin */
    double *two_area = (double *)malloc(sizeof(double) * 2 * (size_t)(B * T > 0 ? B * T : 1)), *longest = NULL;
    int *any_thin = (int *)calloc((size_t)(B > 0 ? B : 1), sizeof(int));
    if (two_area == NULL || any_thin == NULL) { /* no point regular: the caller computes them all */
        memset(GX, 0, sizeof(double) * 3 * (size_t)(B * n));
        memset(reg, 0, (size_t)(B * n));
        free(two_area);
        free(any_thin);
        return;
    }
    longest = two_area + B * T;
    for (long b = 0; b < B; ++b)
        for (long f = 0; f < T; ++f) {
            const double *Pb = P + 3 * V * b;
            const double *p0 = Pb + 3 * tri[3 * f], *p1 = Pb + 3 * tri[3 * f + 1], *p2 = Pb + 3 * tri[3 * f + 2];
            double e1[3], e2[3], e3[3], c[3];
            for (int k = 0; k < 3; ++k) e1[k] = p1[k] - p0[k], e2[k] = p2[k] - p0[k], e3[k] = p2[k] - p1[k];
            cross3(e1, e2, c);
            two_area[T * b + f] = sqrt(dot3(c, c));
            double l = fmax(fmax(dot3(e1, e1), dot3(e2, e2)), dot3(e3, e3));
            longest[T * b + f] = sqrt(l);
            any_thin[b] |= two_area[T * b + f] > 0 && l > TC_THIN_ASPECT * two_area[T * b + f];
        }
    const long nb = (n + VL - 1) / VL;
#pragma omp parallel num_threads(nthreads)
    {
        /* face scratch, raw weights and their cotangent, the vertex gradients lane by lane */
        size_t size = (size_t)TC_FA_SIZE * T * VL + 5 * (size_t)V * VL;
        double *ws = (double *)malloc(sizeof(double) * size), *gpl = ws ? ws + size - 3 * (size_t)V * VL : NULL;
        for (long b = 0; b < B; ++b) {
            const double *Pb = P + 3 * V * b;
            if (gpl != NULL) memset(gpl, 0, sizeof(double) * 3 * (size_t)V * VL);
            /* (nowait: each thread adds its own lanes' sums below, whatever the others are doing) */
#pragma omp for schedule(dynamic, 8) nowait
            for (long i = 0; i < nb; ++i) {
                const long p0 = VL * i;
                const int cnt = n - p0 < VL ? (int)(n - p0) : VL;
                double *gx = GX + 3 * n * b;
                unsigned char *rg = reg + n * b;
                if (ws == NULL) { /* no scratch: these points are left to the caller (not regular) */
                    for (int l = 0; l < cnt; ++l) {
                        gx[3 * (p0 + l)] = gx[3 * (p0 + l) + 1] = gx[3 * (p0 + l) + 2] = 0.0;
                        rg[p0 + l] = 0;
                    }
                    continue;
                }
                vjp_block(Pb, V, tri, T, two_area + T * b, longest + T * b, any_thin[b], X + 3 * n * b, G + n * V * b,
                          p0, cnt, tol[b], near_c, cancel_c, far_always, ws, gpl, gx, rg);
            }
            if (gpl != NULL) {
#pragma omp critical
                for (long v = 0; v < V; ++v)
                    for (int c = 0; c < 3; ++c) {
                        double sum = 0.0;
                        for (int l = 0; l < VL; ++l) sum += gpl[(3 * v + c) * VL + l];
                        GP[3 * (V * b + v) + c] += sum;
                    }
            }
        }
        free(ws);
    }
    free(two_area);
    free(any_thin);
}

void tc_mvc3d_vjp(const double *P, long V, const int *tri, long T, const double *X, long n, const double *G,
                  double tol, double near_c, double cancel_c, double far_always, int nthreads, double *GX,
                  double *GP, unsigned char *reg) {
    vjp_run(1, P, V, tri, T, X, n, G, &tol, near_c, cancel_c, far_always, nthreads, GX, GP, reg);
}

/* tc_mvc3d_vjp for B cages with one topology: P (B, V, 3), X (B, n, 3), G (B, n, V), tol (B,);
 * GX (B, n, 3), GP (B, V, 3), reg (B, n). Element by element the products of tc_mvc3d_vjp. */
void tc_mvc3d_vjp_batch(long B, const double *P, long V, const int *tri, long T, const double *X, long n,
                        const double *G, const double *tol, double near_c, double cancel_c, double far_always,
                        int nthreads, double *GX, double *GP, unsigned char *reg) {
    vjp_run(B, P, V, tri, T, X, n, G, tol, near_c, cancel_c, far_always, nthreads, GX, GP, reg);
}
