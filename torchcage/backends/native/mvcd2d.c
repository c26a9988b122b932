/* Analytic gradients and Hessians of 2D mean value coordinates (closed polygons).
 *
 * Edge (j, k) adds t / r_j to w_j and t / r_k to w_k, t = tan(alpha / 2) of the signed angle at x
 * between a_j = p_j - x and a_k = p_k - x. With c = a_j x a_k (affine in x), d = a_j.a_k and
 * r = |a|, t = c / (r_j r_k + d) when d >= 0 and (r_j r_k - d) / c otherwise: both forms are free
 * of cancellation, so t is exact to rounding everywhere off the edge, its support line included
 * (where t = 0 smoothly). Every quantity is evaluated as a jet (value, gradient, Hessian; jet.h),
 * the 2D case using the first two gradient entries and Hessian entries xx, yy, xy (slots 0, 1, 3).
 * Normalisation as in mvcd3d.c. Points on the polygon (within tol) are flagged in `on` and get
 * the linear interpolant along their edge and its derivative (Lagrange at a vertex, derivative 0).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "jet.h"
#include "native.h"

static inline jet j2(double v, double gx, double gy, double hxx, double hyy, double hxy) {
    jet r = {v, {gx, gy, 0}, {hxx, hyy, 0, hxy, 0, 0}};
    return r;
}

/* One polygon: P (V, 2); edges (E, 2) int32; X (n, 2). Writes L (n, V), G (n, V, 2), H (n, V, 2, 2)
 * (order 2) and the flags on (n,). Returns 1 where a thread could not allocate its scratch. */
static int mvcd2d_one(const double *P, long V, const int *edges, long NE, const double *X, long n, double tol,
                      int order, int nthreads, double *L, double *G, double *H, unsigned char *on) {
    double centre[2];
    const double far2 = tc_far_centre(P, V, 2, 1, 2, centre);
    int failed = 0; /* a thread could not allocate its scratch */
#pragma omp parallel num_threads(nthreads)
    {
        double *acc = (double *)malloc(sizeof(double) * 6 * (size_t)(V > 0 ? V : 1));
        if (acc == NULL) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp barrier
        if (failed) goto done; /* (every thread: none enters the worksharing loop) */
#pragma omp for schedule(dynamic, 64)
        for (long p = 0; p < n; p++) {
            const double x0 = X[2 * p], x1 = X[2 * p + 1];
            memset(acc, 0, sizeof(double) * 6 * V);
            int flag = 0, oj = 0, ok = 0;
            /* Next to an edge seen under an obtuse angle, t = (r_j r_k - d) / c grows like one over
             * the distance, and so does the total weight: their ratio's derivatives would cancel
             * (an error eps / distance). So every weight is multiplied by c* = c of the edge of
             * smallest |c| among those (the same coordinates once normalised), and that edge's t c*
             * is taken as r_j r_k - d, without the division. */
            long best = -1;
            double cbest = INFINITY;
            jet cstar = j2(1.0, 0, 0, 0, 0, 0);
            for (long e = 0; e < NE; e++) {
                int j = edges[2 * e], k = edges[2 * e + 1];
                double aj0 = P[2 * j] - x0, aj1 = P[2 * j + 1] - x1, ak0 = P[2 * k] - x0, ak1 = P[2 * k + 1] - x1;
                double cv = aj0 * (P[2 * k + 1] - P[2 * j + 1]) - aj1 * (P[2 * k] - P[2 * j]), dv = aj0 * ak0 + aj1 * ak1;
                if (dv < 0 && cv != 0 && fabs(cv) < cbest) {
                    cbest = fabs(cv), best = e;
                    cstar = j2(cv, P[2 * j + 1] - P[2 * k + 1], -(P[2 * j] - P[2 * k]), 0, 0, 0);
                }
            }
            for (long e = 0; e < NE; e++) {
                int j = edges[2 * e], k = edges[2 * e + 1];
                double aj0 = P[2 * j] - x0, aj1 = P[2 * j + 1] - x1, ak0 = P[2 * k] - x0, ak1 = P[2 * k + 1] - x1;
                double E0 = P[2 * j] - P[2 * k], E1 = P[2 * j + 1] - P[2 * k + 1];
                double ell = sqrt(E0 * E0 + E1 * E1);
                /* c = a_j x (p_k - p_j): the edge from the vertices, exact far away (a_j x a_k loses
                 * eps |a| / |E| of itself to cancellation there) */
                jet c = j2(-aj0 * E1 + aj1 * E0, E1, -E0, 0, 0, 0);
                jet d = j2(aj0 * ak0 + aj1 * ak1, -(aj0 + ak0), -(aj1 + ak1), 2, 2, 0);
                jet rj = j_sqrt(j2(aj0 * aj0 + aj1 * aj1, -2 * aj0, -2 * aj1, 2, 2, 0));
                jet rk = j_sqrt(j2(ak0 * ak0 + ak1 * ak1, -2 * ak0, -2 * ak1, 2, 2, 0));
                if (rj.v <= tol || rk.v <= tol || (fabs(c.v) <= tol * ell && d.v <= 0)) {
                    flag = 1, oj = j, ok = k;
                    break;
                }
                jet rr = j_mul(rj, rk);
                jet t = e == best ? j_sub(rr, d) : j_mul(cstar, d.v >= 0 ? j_div(c, j_add(rr, d)) : j_div(j_sub(rr, d), c));
                jet wj = j_div(t, rj), wk = j_div(t, rk);
                const jet *ws[2] = {&wj, &wk};
                int vs[2] = {j, k};
                for (int s = 0; s < 2; s++) {
                    double *ac = acc + 6 * vs[s];
                    ac[0] += ws[s]->v;
                    ac[1] += ws[s]->g[0], ac[2] += ws[s]->g[1];
                    ac[3] += ws[s]->h[0], ac[4] += ws[s]->h[1], ac[5] += ws[s]->h[3];
                }
            }
            on[p] = (unsigned char)flag;
            if (flag) {  // on the polygon: the linear interpolant along the edge and its derivative
                memset(L + p * V, 0, sizeof(double) * V);
                memset(G + p * V * 2, 0, sizeof(double) * V * 2);
                if (order >= 2) memset(H + p * V * 4, 0, sizeof(double) * V * 4);
                double e0 = P[2 * ok] - P[2 * oj], e1 = P[2 * ok + 1] - P[2 * oj + 1], l2 = e0 * e0 + e1 * e1;
                double t = ((x0 - P[2 * oj]) * e0 + (x1 - P[2 * oj + 1]) * e1) / l2;
                t = t < 0 ? 0 : (t > 1 ? 1 : t);
                L[p * V + oj] = 1.0 - t, L[p * V + ok] = t;
                if (t > 0 && t < 1) {
                    G[(p * V + ok) * 2] = e0 / l2, G[(p * V + ok) * 2 + 1] = e1 / l2;
                    G[(p * V + oj) * 2] = -e0 / l2, G[(p * V + oj) * 2 + 1] = -e1 / l2;
                }
                continue;
            }
            static const int HI[3] = {0, 1, 0}, HJ[3] = {0, 1, 1};
            const double y0 = x0 - centre[0], y1 = x1 - centre[1], y2 = y0 * y0 + y1 * y1;
            if (y2 > far2) {
                /* Far from the polygon the sum of the weights cancels: normalise by their first
                 * moment M = (sum_v w_v (P_v - c)) . y / |y|^2, y = x - c (as in mvcd3d.c). */
                jet S0 = j_const(0.0), S1 = j_const(0.0);
                for (long v = 0; v < V; v++) {
                    const double *ac = acc + 6 * v;
                    jet wv = j2(ac[0], ac[1], ac[2], ac[3], ac[4], ac[5]);
                    S0 = j_add(S0, j_scale(wv, P[2 * v] - centre[0]));
                    S1 = j_add(S1, j_scale(wv, P[2 * v + 1] - centre[1]));
                }
                jet num = j_add(j_mul(S0, j2(y0, 1, 0, 0, 0, 0)), j_mul(S1, j2(y1, 0, 1, 0, 0, 0)));
                jet M = j_div(num, j2(y2, 2 * y0, 2 * y1, 2, 2, 0));
                if (!(M.v != 0.0) || !isfinite(M.v)) {
                    on[p] = 2;
                    continue;
                }
                jet iM = j_recip(M);
                for (long v = 0; v < V; v++) {
                    const double *ac = acc + 6 * v;
                    jet lam = j_mul(j2(ac[0], ac[1], ac[2], ac[3], ac[4], ac[5]), iM);
                    L[p * V + v] = lam.v;
                    G[(p * V + v) * 2] = lam.g[0], G[(p * V + v) * 2 + 1] = lam.g[1];
                    if (order < 2) continue;
                    double *Hp = H + (p * V + v) * 4;
                    Hp[0] = lam.h[0], Hp[3] = lam.h[1], Hp[1] = Hp[2] = lam.h[3];
                }
                continue;
            }
            double W = 0, gW[2] = {0, 0}, HW[3] = {0, 0, 0};
            for (long v = 0; v < V; v++) {
                W += acc[6 * v];
                gW[0] += acc[6 * v + 1], gW[1] += acc[6 * v + 2];
                HW[0] += acc[6 * v + 3], HW[1] += acc[6 * v + 4], HW[2] += acc[6 * v + 5];
            }
            if (!(W != 0.0) || !isfinite(W)) {
                on[p] = 2;
                continue;
            }
            double iW = 1.0 / W;
            for (long v = 0; v < V; v++) {
                const double *ac = acc + 6 * v;
                double lam = ac[0] * iW, gl[2];
                L[p * V + v] = lam;
                for (int c = 0; c < 2; c++) {
                    gl[c] = (ac[1 + c] - lam * gW[c]) * iW;
                    G[(p * V + v) * 2 + c] = gl[c];
                }
                if (order < 2) continue;
                double *Hp = H + (p * V + v) * 4;
                for (int k = 0; k < 3; k++) {
                    int a = HI[k], b = HJ[k];
                    double val = (ac[3 + k] - lam * HW[k] - gl[a] * gW[b] - gW[a] * gl[b]) * iW;
                    Hp[2 * a + b] = val;
                    Hp[2 * b + a] = val;
                }
            }
        }
    done:
        free(acc);
    }
    return failed;
}

/* The derivatives of a batch of B polygons with one topology (vertices P (B, V, 2), on-polygon
 * tolerances tol (B,)) at points X (XB, n, 2), XB = 1 (shared) or B: L (B, n, V), G (B, n, V, 2),
 * H (B, n, V, 2, 2) (order 2) and on (B, n) as in mvcd2d_one, the polygons one after the other,
 * each parallel over its points. A failed allocation makes every row NaN and every flag 3 (the
 * glue raises MemoryError). XB must be 1 or B (the glue checks). */
void tc_mvcd2d(long B, const double *P, long V, const int *edges, long NE, const double *X, long XB, long n,
               const double *tol, int order, int nthreads, double *L, double *G, double *H, unsigned char *on) {
    int failed = 0;
    for (long b = 0; b < B && !failed; ++b)
        failed = mvcd2d_one(P + b * V * 2, V, edges, NE, X + (XB > 1 ? b : 0) * n * 2, n, tol[b], order, nthreads,
                            L + b * n * V, G + b * n * V * 2, order >= 2 ? H + b * n * V * 4 : H, on + b * n);
    if (failed) {
        for (long k = 0; k < B * n * V; ++k) L[k] = NAN;
        memset(on, 3, (size_t)(B * n));
    }
}
