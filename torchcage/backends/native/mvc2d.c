/*
 * Native CPU kernel of torchcage's 2D mean value coordinates (float64): the same formulas as
 * torchcage/families/mean_value/kernel2d.py (half-angle tangents in their non-cancelling form, linear
 * interpolation on the polygon), one point per iteration, OpenMP over points.
 */
#define _GNU_SOURCE
#include <math.h>
#include <string.h>

#include "native.h"

/* One polygon: P (V, 2) vertices; edges (E, 2) int32 directed edges (counter-clockwise); X (n, 2)
 * points. Output W (n, V) normalised coordinates; on[p] = 1 for points on the polygon, 2 where a
 * coordinate is not finite (the total weight vanishes: only outside the polygon). */
static void mvc2d_one(const double *P, long V, const int *edges, long E, const double *X, long n, double tol,
                      int nthreads, double *W, unsigned char *on) {
    double centre[2];
    const double far2 = tc_far_centre(P, V, 2, 1, 2, centre);
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (long p = 0; p < n; ++p) {
        const double x0 = X[2 * p], x1 = X[2 * p + 1];
        double *w = W + p * V;
        memset(w, 0, sizeof(double) * (size_t)V);
        on[p] = 0;
        for (long q = 0; q < E; ++q) {
            int j = edges[2 * q], k = edges[2 * q + 1];
            double ajx = P[2 * j] - x0, ajy = P[2 * j + 1] - x1, akx = P[2 * k] - x0, aky = P[2 * k + 1] - x1;
            double ex = P[2 * k] - P[2 * j], ey = P[2 * k + 1] - P[2 * j + 1];
            double Rj = sqrt(ajx * ajx + ajy * ajy), Rk = sqrt(akx * akx + aky * aky);
            double cross = ajx * ey - ajy * ex, dot = ajx * akx + ajy * aky, RR = Rj * Rk;
            double ell2 = ex * ex + ey * ey, ell = sqrt(ell2);
            double t = -(ajx * ex + ajy * ey) / ell2;
            if ((fabs(cross) / ell <= tol && t >= -tol / ell && t <= 1 + tol / ell) || Rj <= tol || Rk <= tol) {
                double tt = Rj <= tol ? 0.0 : (Rk <= tol ? 1.0 : (t < 0 ? 0.0 : (t > 1 ? 1.0 : t)));
                memset(w, 0, sizeof(double) * (size_t)V);
                w[j] += 1.0 - tt;
                w[k] += tt;
                on[p] = 1;
                break;
            }
            double tan_half = dot >= 0 ? cross / (RR + dot) : (cross != 0 ? (RR - dot) / cross : 0.0);
            w[j] += tan_half / Rj;
            w[k] += tan_half / Rk;
        }
        if (on[p]) continue;
        double inv = 1.0 / tc_mv_total(w, V, P, 2, 1, 2, X + 2 * p, centre, far2);
        int finite = 1;
        for (long v = 0; v < V; ++v) {
            w[v] *= inv;
            finite &= isfinite(w[v]) != 0;
        }
        if (!finite) on[p] = 2;
    }
}

/* 2D mean value coordinates of a batch of B polygons with one topology (vertices P (B, V, 2),
 * on-polygon tolerances tol (B,)): points X (XB, n, 2), XB = 1 (shared by every polygon) or B;
 * W (B, n, V) and the flags on (B, n) as in mvc2d_one. The polygons one after the other, each
 * parallel over its points. XB must be 1 or B (the glue checks). */
void tc_mvc2d(long B, const double *P, long V, const int *edges, long E, const double *X, long XB, long n,
              const double *tol, int nthreads, double *W, unsigned char *on) {
    for (long b = 0; b < B; ++b)
        mvc2d_one(P + b * V * 2, V, edges, E, X + (XB > 1 ? b : 0) * n * 2, n, tol[b], nthreads, W + b * n * V,
                  on + b * n);
}
