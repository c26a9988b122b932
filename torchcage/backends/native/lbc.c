/*
 * Native CPU iterations of LBC's ADMM (float64): the loop of torchcage/solvers/lbc.py (solve_lbc),
 * the same steps and formulas, in four passes over memory per iteration.
 *
 * Every block is row-major with the V cage vertices (the coordinate functions) contiguous, so that
 * each inner loop runs over them and vectorises: the gradient blocks P1, u1, J are (D C, V) with row
 * d C + s the d-th component on cell s, phiA is (C, V), the interior blocks P2, u2, H are (m, V).
 *
 * The Y step solves (G^T G + s^2 I) Yhat = Z (I - Q Q^T) for all V right-hand sides at once, with
 * Yhat = Y M the update of the interior values (M^T M = I - Q Q^T, Q (V, D+1) an orthonormal basis
 * of the columns of K, so that Yhat K = 0 and the constraints W K = B stay exact): forward and back
 * substitution with a sparse LU factorisation computed once (A = Pr^T L U Pc^T, L unit lower, as
 * scipy's splu returns it): the right-hand side of unknown i goes to row pr[i], its solution is
 * read from row pc[i] (G's column indices g_idx are given already mapped through pc).
 *
 * Pass 1 (per cell): group shrinkage of a = P1 - u1 (Eq. 30), over-relaxation; writes
 *   qJ = q - J (q = lerp(P1, X, alpha) + u1) and, on the last iteration, X.
 * Pass 2 (per interior vertex): Z = s^2 (w - H) + G^T qJ with w = lerp(P2, max(P2 - u2 / s, 0), alpha)
 *   + u2 / s; projected; scattered to the permuted rows. Then the two triangular solves.
 * Pass 3 (per interior vertex): P2' = H + Yhat, u2 = (w - P2') s.
 * Pass 4 (per gradient row): T = G Yhat, P1' = J + T, u1 = qJ - T.
 * On the last iteration res[0] = ||X - P1'||^2 + ||W - P2'||^2 and res[1] = ||P1' - P1||^2 +
 * ||P2' - P2||^2 (the squared primal residual and the squared dual residual over mu^2).
 *
 * Passes 1, 3 and 4 run in parallel over rows (OpenMP, nthreads); each row is computed alone, so
 * the iterates do not depend on the thread count. The triangular solves are sequential.
 */
#include <math.h>

/* torch.lerp(a, b, t) for t >= 0.5, the branch the solver's relaxation (t in [1.5, 1.8]) takes:
 * b - (b - a) (1 - t); for t < 0.5, a + t (b - a). Written as torch does, for the same rounding. */
static inline double lerp_(double a, double b, double t) { return t < 0.5 ? a + t * (b - a) : b - (b - a) * (1.0 - t); }

void tc_lbc_admm(long D, long C, long m, long V, const int *g_ptr, const int *g_idx, const double *g_val, long g_nnz,
                 const int *gt_ptr, const int *gt_idx, const double *gt_val, long gt_nnz, const int *l_ptr,
                 const int *l_idx, const double *l_val, long l_nnz, const int *u_ptr, const int *u_idx,
                 const double *u_val, long u_nnz, const double *u_diag, const int *pr, const int *pc, const double *J,
                 const double *H, const double *phiA, const double *Q, double mu, double alpha, double ws,
                 long iters, int nthreads, double *P1, double *P2, double *u1, double *u2, double *work,
                 double *res) {
    (void)g_nnz;
    (void)gt_nnz;
    (void)l_nnz;
    (void)u_nnz;
    const long R = D * C;
    const long K1 = D + 1;
    double *qJ = work;              /* (D C, V) */
    double *X = qJ + R * V;         /* (D C, V), last iteration only */
    double *w = X + R * V;          /* (m, V) */
    double *Y = w + m * V;          /* (m, V), permuted rows */
    const double ws2 = ws * ws, inv_ws = 1.0 / ws, inv_mu = -1.0 / mu;
    double rp = 0.0, rd = 0.0;
    for (long it = 0; it < iters; ++it) {
        const int last = it == iters - 1;
        /* Pass 1: shrinkage and relaxation, one cell (D rows) at a time. */
#pragma omp parallel for num_threads(nthreads) schedule(static)
        for (long s = 0; s < C; ++s) {
            double nrm[V > 0 ? V : 1];
            for (long v = 0; v < V; ++v) nrm[v] = 0.0;
            for (long d = 0; d < D; ++d) {
                const double *p = P1 + (d * C + s) * V, *u = u1 + (d * C + s) * V;
                for (long v = 0; v < V; ++v) {
                    double a = p[v] - u[v];
                    nrm[v] += a * a;
                }
            }
            const double *phi = phiA + s * V;
            for (long v = 0; v < V; ++v) {
                double n = sqrt(nrm[v]);
                n = n > 1e-300 ? n : 1e-300;
                double sh = phi[v] / n * inv_mu + 1.0;
                nrm[v] = sh > 0.0 ? sh : 0.0;
            }
            for (long d = 0; d < D; ++d) {
                const long o = (d * C + s) * V;
                const double *p = P1 + o, *u = u1 + o, *j = J + o;
                double *out = qJ + o;
                for (long v = 0; v < V; ++v) {
                    double x = (p[v] - u[v]) * nrm[v];
                    out[v] = (lerp_(p[v], x, alpha) + u[v]) - j[v];
                }
                if (last)
                    for (long v = 0; v < V; ++v) X[o + v] = (p[v] - u[v]) * nrm[v];
            }
        }
        /* Pass 2: right-hand sides, projected, to their permuted rows. */
#pragma omp parallel for num_threads(nthreads) schedule(static)
        for (long i = 0; i < m; ++i) {
            double z[V > 0 ? V : 1], c[8];
            for (long v = 0; v < V; ++v) z[v] = 0.0;
            for (int e = gt_ptr[i]; e < gt_ptr[i + 1]; ++e) {
                const double g = gt_val[e], *q = qJ + (long)gt_idx[e] * V;
                for (long v = 0; v < V; ++v) z[v] += g * q[v];
            }
            const double *p = P2 + i * V, *u = u2 + i * V, *h = H + i * V;
            double *wi = w + i * V;
            for (long v = 0; v < V; ++v) {
                double W = p[v] - u[v] / ws;
                W = W > 0.0 ? W : 0.0;
                wi[v] = lerp_(p[v], W, alpha) + u[v] * inv_ws;
                z[v] += ws2 * (wi[v] - h[v]);
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
        /* The triangular solves, column-oriented (CSC), all right-hand sides at once. */
        for (long jc = 0; jc < m; ++jc) {
            const double *yj = Y + jc * V;
            for (int e = l_ptr[jc]; e < l_ptr[jc + 1]; ++e) {
                const double l = l_val[e];
                double *yi = Y + (long)l_idx[e] * V;
                for (long v = 0; v < V; ++v) yi[v] -= l * yj[v];
            }
        }
        for (long jc = m - 1; jc >= 0; --jc) {
            double *yj = Y + jc * V;
            const double dg = u_diag[jc];
            for (long v = 0; v < V; ++v) yj[v] /= dg;
            for (int e = u_ptr[jc]; e < u_ptr[jc + 1]; ++e) {
                const double uv = u_val[e];
                double *yi = Y + (long)u_idx[e] * V;
                for (long v = 0; v < V; ++v) yi[v] -= uv * yj[v];
            }
        }
        /* Pass 3: interior values and their multipliers. */
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
        /* Pass 4: gradients of the new values and their multipliers. */
#pragma omp parallel for num_threads(nthreads) schedule(static) reduction(+ : rp, rd)
        for (long r = 0; r < R; ++r) {
            double t[V > 0 ? V : 1];
            for (long v = 0; v < V; ++v) t[v] = 0.0;
            for (int e = g_ptr[r]; e < g_ptr[r + 1]; ++e) {
                const double g = g_val[e], *y = Y + (long)g_idx[e] * V;
                for (long v = 0; v < V; ++v) t[v] += g * y[v];
            }
            const double *j = J + r * V, *q = qJ + r * V;
            double *p = P1 + r * V, *u = u1 + r * V;
            if (last) {
                const double *x = X + r * V;
                for (long v = 0; v < V; ++v) {
                    double pn = j[v] + t[v];
                    rp += (x[v] - pn) * (x[v] - pn);
                    rd += (pn - p[v]) * (pn - p[v]);
                }
            }
            for (long v = 0; v < V; ++v) {
                p[v] = j[v] + t[v];
                u[v] = q[v] - t[v];
            }
        }
    }
    res[0] = rp;
    res[1] = rd;
}
