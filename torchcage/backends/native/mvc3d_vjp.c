/*
 * Vector-Jacobian products of 3D mean value coordinates with respect to the query points and the
 * rest cage's vertices at once (float64): the hand-derived reverse mode of the direct vector form,
 * the same formulas and the same "regular point" test as torchcage/families/mean_value/vjp3d.py (its
 * docstring gives the derivation). One point per iteration, OpenMP over points; each thread sums
 * its vertex gradients in its own buffer, added up at the end.
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

/* Per-face scratch of the forward pass, reused by the reverse pass. */
enum { S_A = TC_FA_A, S_N = TC_FA_N, S_NN = TC_FA_NN, S_D = TC_FA_D, S_TH = TC_FA_TH, S_G = TC_FA_G, S_M = TC_FA_M,
       S_DET = TC_FA_DET, S_W = TC_FA_W, S_SIZE = TC_FA_SIZE };

void tc_mvc3d_vjp(const double *P, long V, const int *tri, long T, const double *X, long n, const double *G,
                  double tol, double near_c, double cancel_c, double far_always, int nthreads, double *GX,
                  double *GP, unsigned char *reg) {
    double *two_area = (double *)malloc(sizeof(double) * 2 * (size_t)T), *longest = two_area + T;
    int any_thin = 0;
    for (long f = 0; f < T; ++f) {
        const double *p0 = P + 3 * tri[3 * f], *p1 = P + 3 * tri[3 * f + 1], *p2 = P + 3 * tri[3 * f + 2];
        double e1[3], e2[3], e3[3], c[3];
        for (int k = 0; k < 3; ++k) e1[k] = p1[k] - p0[k], e2[k] = p2[k] - p0[k], e3[k] = p2[k] - p1[k];
        cross3(e1, e2, c);
        two_area[f] = sqrt(dot3(c, c));
        double l = fmax(fmax(dot3(e1, e1), dot3(e2, e2)), dot3(e3, e3));
        longest[f] = sqrt(l);
        any_thin |= two_area[f] > 0 && l > TC_THIN_ASPECT * two_area[f];
    }
    memset(GP, 0, sizeof(double) * 3 * (size_t)V);
#pragma omp parallel num_threads(nthreads)
    {
        double *S = (double *)malloc(sizeof(double) * ((size_t)S_SIZE * (size_t)T + 5 * (size_t)V));
        double *Wv = S + (size_t)S_SIZE * T, *wbar = Wv + V, *gp = wbar + V;
        memset(gp, 0, sizeof(double) * 3 * (size_t)V);
#pragma omp for schedule(dynamic, 32)
        for (long p = 0; p < n; ++p) {
            const double *x = X + 3 * p;
            const double *g = G + p * V;
            double *gx = GX + 3 * p;
            gx[0] = gx[1] = gx[2] = 0.0;
            reg[p] = 0;
            memset(Wv, 0, sizeof(double) * (size_t)V);
            int ok = 1;
            double abs_sum = 0.0;
            for (long f = 0; f < T && ok; ++f) {
                double *s = S + (size_t)S_SIZE * f, *a = s + S_A, *N = s + S_N, *m = s + S_M, *w = s + S_W;
                double R[3], rmin = tc_mvc_face_direct(P, tri + 3 * f, x, s, R), det = s[S_DET];
                if (!(fabs(det) >= near_c * rmin * two_area[f] && rmin > tol && longest[f] * far_always >= rmin) ||
                    (any_thin && longest[f] * longest[f] > TC_THIN_ASPECT * two_area[f] &&
                     tc_thin_face((const double(*)[3])a, two_area[f]))) {
                    ok = 0;
                    break;
                }
                double fsum = 0.0;
                for (int i = 0; i < 3; ++i) {
                    w[i] = dot3(N + 3 * i, m) / det;
                    Wv[tri[3 * f + i]] += w[i];
                    fsum += w[i];
                }
                abs_sum += fabs(fsum);
            }
            if (!ok) continue;
            double total = 0.0;
            for (long v = 0; v < V; ++v) total += Wv[v];
            if (!(abs_sum <= cancel_c * fabs(total)) || total == 0.0) continue;
            reg[p] = 1;
            double sg = 0.0;
            for (long v = 0; v < V; ++v) sg += g[v] * Wv[v];
            sg /= total;
            for (long v = 0; v < V; ++v) wbar[v] = (g[v] - sg) / total;
            for (long f = 0; f < T; ++f) tc_mvc_face_adjoint(S + (size_t)S_SIZE * f, tri + 3 * f, wbar, gp, gx);
        }
#pragma omp critical
        for (long k = 0; k < 3 * V; ++k) GP[k] += gp[k];
        free(S);
    }
    free(two_area);
}
