/*
 * Native CPU iterations of LBC's ADMM (float64): the loop of torchcage/solvers/lbc.py (solve_lbc),
 * the same steps and formulas, in three passes over memory per iteration.
 *
 * Every block is row-major with the cage vertices (the coordinate functions) contiguous, V of them
 * padded with zero columns to a multiple of 4 (the caller pads; the padding stays exactly 0), so that
 * every inner loop runs over whole groups of 4 and vectorises: the gradient blocks P1, u1 are
 * (D C, V) with row d C + s the d-th component on cell s, phiA is (C, V), the interior blocks u2,
 * H, GtJ = G^T J are (m, V), and P2 is (m + nb, V): the m interior values, then the nb boundary
 * values (constant), so that the gradients G P1 + E = Gf P2 are one sparse product (Gf: the
 * gradient operator of all the mesh's vertices, its columns renumbered in this order).
 *
 * The Y step solves (G^T G + s^2 I) Yhat = Z (I - Q^T Q) for all V right-hand sides at once, with
 * Yhat = Y M the update of the interior values (M^T M = I - Q^T Q, the rows of Q (D+1, V) an
 * orthonormal basis of the columns of K, so that Yhat K = 0 and the constraints W K = B stay exact):
 * forward and back substitution with a sparse LU factorisation computed once (A = Pr^T L U Pc^T, L
 * unit lower, as scipy's splu returns it; here the strict triangles by rows, CSR): the right-hand
 * side of unknown i goes to row pr[i], its solution is read from row pc[i].
 *
 * One iteration:
 *   A (per cell, D rows): group shrinkage of a = P1 - u1 (Eq. 30) and over-relaxation,
 *     q = lerp(P1, X, alpha) + u1.
 *   B (per interior vertex): Z = s^2 (w - H) + G^T q - G^T J, w = lerp(P2, W, alpha) + u2 / s with
 *     W = max(P2 - u2 / s, 0) (Eq. 31); projected; scattered to the permuted rows. The two
 *     triangular solves.
 *   C (per interior vertex): P2' = H + Yhat, u2 = (w - P2') s.
 *   D (per cell): P1' = Gf P2', u1 = q - P1'; then step A of the next iteration on the same rows
 *     (P1' and u1 never leave the cache; they are stored only after the last iteration).
 * After the last iteration res[0] = ||X - P1'||^2 + ||W - P2'||^2 and res[1] = ||P1' - P1||^2 +
 * ||P2' - P2||^2 (the squared primal residual, and the squared dual residual over mu^2).
 *
 * Steps A, B (its first part), C and D run in parallel over rows (OpenMP, nthreads); each row is
 * computed alone, so the iterates do not depend on the thread count. The triangular solves are
 * sequential.
 */
#include <math.h>
#include <stddef.h>
#ifdef _OPENMP
#include <omp.h>
#define TC_LBC_THREAD omp_get_thread_num()
#else
#define TC_LBC_THREAD 0
#endif

/* torch.lerp(a, b, t), as torch computes it (the same rounding): b - (b - a) (1 - t) for t >= 0.5,
 * the branch the solver's relaxation (t in [1.5, 1.8]) takes, else a + t (b - a). */
static inline double lerp_(double a, double b, double t) { return t < 0.5 ? a + t * (b - a) : b - (b - a) * (1.0 - t); }

/* Step A on cell s: from its rows p = P1, u = u1 (D rows of V, row strides ps, us) to q (at rows
 * d C + s) and, when X is not NULL, X; sh: V of scratch. */
static inline void shrink_cell(long D, long C, long V, long s, const double *p, long ps, const double *u, long us,
                               const double *phiA, double inv_mu, double alpha, double *q, double *X, double *sh) {
    for (long v = 0; v < V; ++v) sh[v] = 0.0;
    for (long d = 0; d < D; ++d)
        for (long v = 0; v < V; ++v) {
            double a = p[d * ps + v] - u[d * us + v];
            sh[v] += a * a;
        }
    const double *phi = phiA + s * V;
    for (long v = 0; v < V; ++v) {
        double n = sqrt(sh[v]);
        n = n > 1e-300 ? n : 1e-300;
        double f = phi[v] / n * inv_mu + 1.0;
        sh[v] = f > 0.0 ? f : 0.0;
    }
    for (long d = 0; d < D; ++d) {
        const long o = (d * C + s) * V;
        const double *pd = p + d * ps, *ud = u + d * us;
        double *out = q + o;
        for (long v = 0; v < V; ++v) {
            double x = (pd[v] - ud[v]) * sh[v];
            out[v] = lerp_(pd[v], x, alpha) + ud[v];
        }
        if (X)
            for (long v = 0; v < V; ++v) X[o + v] = (pd[v] - ud[v]) * sh[v];
    }
}

/* out (V) = init - sum over e in [e0, e1) of val[e] * rows[idx[e]] (rows of V; init NULL: 0), with
 * sixteen, eight or four columns at a time in registers: independent sums, so that the additions'
 * latency overlaps. (The sum is formed first and subtracted once: the same rounding as init - sum.) */
#define TC_LBC_BLOCK(W)                                                                                \
    for (; b + (W) <= V; b += (W)) {                                                                   \
        double acc[W];                                                                                 \
        for (int k = 0; k < (W); ++k) acc[k] = 0.0;                                                    \
        for (int e = e0; e < e1; ++e) {                                                                \
            const double g = val[e], *y = rows + (long)idx[e] * V + b;                                 \
            for (int k = 0; k < (W); ++k) acc[k] += g * y[k];                                          \
        }                                                                                              \
        if (init)                                                                                      \
            for (int k = 0; k < (W); ++k) out[b + k] = init[b + k] - acc[k];                           \
        else                                                                                           \
            for (int k = 0; k < (W); ++k) out[b + k] = -acc[k];                                        \
    }

static inline void sparse_row(long V, int e0, int e1, const int *idx, const double *val, const double *rows,
                              const double *init, double *out) {
    long b = 0;
    TC_LBC_BLOCK(16)
    TC_LBC_BLOCK(8)
    TC_LBC_BLOCK(4)
    TC_LBC_BLOCK(1) /* (the caller pads V to a multiple of 4; any other V is served whole all the same) */
}

void tc_lbc_admm(long D, long C, long m, long V, const int *g_ptr, const int *g_idx, const double *g_val, long g_nnz,
                 const int *gt_ptr, const int *gt_idx, const double *gt_val, long gt_nnz, const int *l_ptr,
                 const int *l_idx, const double *l_val, long l_nnz, const int *u_ptr, const int *u_idx,
                 const double *u_val, long u_nnz, const double *u_diag, const int *pr, const int *pc,
                 long nb, const double *GtJ, const double *H, const double *phiA, const double *Q, double mu,
                 double alpha,
                 double ws, long iters, int nthreads, double *P1, double *P2, double *u1, double *u2, double *work,
                 double *res) {
    (void)g_nnz;
    (void)gt_nnz;
    (void)l_nnz;
    (void)u_nnz;
    (void)nb;
    const long R = D * C, K1 = D + 1;
    (void)nthreads; /* (unused without OpenMP) */
    double *q = work;            /* (D C, V) */
    double *X = q + R * V;       /* (D C, V), the last iteration's */
    double *w = X + R * V;       /* (m, V) */
    double *Y = w + m * V;       /* (m, V), permuted rows */
    double *scratch = Y + m * V; /* (2 D + 2) V per thread (no variable-length arrays: MSVC has none) */
    const double ws2 = ws * ws, inv_ws = 1.0 / ws, inv_mu = -1.0 / mu;
    double rp = 0.0, rd = 0.0;
    if (iters < 1) return;
    /* Step A of the first iteration, from the state. */
#pragma omp parallel num_threads(nthreads)
    {
        double *mine = scratch + TC_LBC_THREAD * (2 * D + 2) * V;
#pragma omp for schedule(static)
        for (long s = 0; s < C; ++s)
            shrink_cell(D, C, V, s, P1 + s * V, C * V, u1 + s * V, C * V, phiA, inv_mu, alpha, q,
                        iters == 1 ? X : NULL, mine);
    }
    for (long it = 0; it < iters; ++it) {
        const int last = it == iters - 1;
        /* Step B: right-hand sides, projected, to their permuted rows. */
#pragma omp parallel num_threads(nthreads)
        {
            double *z = scratch + TC_LBC_THREAD * (2 * D + 2) * V, *c = z + V; /* (V >= D + 1) */
#pragma omp for schedule(static)
            for (long i = 0; i < m; ++i) {
                sparse_row(V, gt_ptr[i], gt_ptr[i + 1], gt_idx, gt_val, q, GtJ + i * V, z); /* G^T J - G^T q */
                const double *p = P2 + i * V, *u = u2 + i * V, *h = H + i * V;
                double *wi = w + i * V;
                for (long v = 0; v < V; ++v) {
                    double W = p[v] - u[v] / ws;
                    W = W > 0.0 ? W : 0.0;
                    wi[v] = lerp_(p[v], W, alpha) + u[v] * inv_ws;
                    z[v] = ws2 * (wi[v] - h[v]) - z[v];
                }
                for (long k = 0; k < K1; ++k) {
                    double acc = 0.0;
                    for (long v = 0; v < V; ++v) acc += z[v] * Q[k * V + v];
                    c[k] = acc;
                }
                double *y = Y + (long)pr[i] * V;
                for (long v = 0; v < V; ++v) {
                    double acc = z[v];
                    for (long k = 0; k < K1; ++k) acc -= c[k] * Q[k * V + v];
                    y[v] = acc;
                }
            }
        }
        /* The triangular solves by rows, all right-hand sides at once, four columns at a time in a
         * register. */
        for (long i = 0; i < m; ++i) sparse_row(V, l_ptr[i], l_ptr[i + 1], l_idx, l_val, Y, Y + i * V, Y + i * V);
        for (long i = m - 1; i >= 0; --i) {
            double *yi = Y + i * V;
            const double dg = u_diag[i];
            sparse_row(V, u_ptr[i], u_ptr[i + 1], u_idx, u_val, Y, yi, yi);
            for (long v = 0; v < V; ++v) yi[v] /= dg;
        }
        /* Step C: interior values and their multipliers. */
#pragma omp parallel for num_threads(nthreads) schedule(static) reduction(+ : rp, rd)
        for (long i = 0; i < m; ++i) {
            const double *y = Y + (long)pc[i] * V, *h = H + i * V, *wi = w + i * V;
            double *p = P2 + i * V, *u = u2 + i * V;
            if (last)
                for (long v = 0; v < V; ++v) {
                    double W = p[v] - u[v] / ws, pn = h[v] + y[v];
                    W = W > 0.0 ? W : 0.0;
                    rp += (W - pn) * (W - pn);
                    rd += (pn - p[v]) * (pn - p[v]);
                }
            for (long v = 0; v < V; ++v) {
                double pn = h[v] + y[v];
                u[v] = (wi[v] - pn) * ws;
                p[v] = pn;
            }
        }
        /* Step D, and step A of the next iteration (of which the last keeps X), one cell at a time;
         * after the last iteration, the state. */
        const int next_last = it == iters - 2;
#pragma omp parallel num_threads(nthreads)
        {
            double *pn = scratch + TC_LBC_THREAD * (2 * D + 2) * V, *un = pn + D * V;
#pragma omp for schedule(static) reduction(+ : rp, rd)
            for (long s = 0; s < C; ++s) {
                for (long d = 0; d < D; ++d) {
                    const long r = d * C + s;
                    double *t = pn + d * V;
                    sparse_row(V, g_ptr[r], g_ptr[r + 1], g_idx, g_val, P2, NULL, t); /* -P1' */
                    const double *qr = q + r * V;
                    double *ud = un + d * V;
                    for (long v = 0; v < V; ++v) {
                        t[v] = -t[v];
                        ud[v] = qr[v] - t[v];
                    }
                    if (last) {
                        const double *x = X + r * V;
                        double *p = P1 + r * V, *u = u1 + r * V;
                        for (long v = 0; v < V; ++v) {
                            rp += (x[v] - t[v]) * (x[v] - t[v]);
                            rd += (t[v] - p[v]) * (t[v] - p[v]);
                            p[v] = t[v];
                            u[v] = ud[v];
                        }
                    } else if (next_last) {
                        double *p = P1 + r * V; /* (the last iteration's dual residual) */
                        for (long v = 0; v < V; ++v) p[v] = t[v];
                    }
                }
                if (!last)
                    shrink_cell(D, C, V, s, pn, V, un, V, phiA, inv_mu, alpha, q, next_last ? X : NULL, un + D * V);
            }
        }
    }
    res[0] = rp;
    res[1] = rd;
}
