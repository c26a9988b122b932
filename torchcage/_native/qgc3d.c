/*
 * Native CPU kernel of the quad part of torchcage's Green coordinates for triquad cages (float64).
 *
 * The same steps as torchcage/functional/_qgc3d.py (see its docstring): per point and quad, the
 * smooth projection (tc_quad_pair, shared with QMVC), the invariants on the fan of four triangles
 * from the projection to the edges (exact triangle Green integrals, tc_tri_green), the least-norm
 * solution through the precomputed pseudo-inverse of A_q, and the null-space part from the adaptive
 * Riemann sum of Algorithm 1. On the Riemann sub-triangles the solid angle is taken in Van
 * Oosterom and Strackee's one-atan2 form (the estimate needs no more); the tests check this kernel
 * against the torch kernel. One point per iteration, OpenMP over points.
 */
#define _GNU_SOURCE
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

#define FOUR_PI 12.566370614359172953850573533118

/* int_e dl / r along an edge (as edge_integral in gc3d.c, without the stored constants). */
static inline double edge_log(double l_j, double l_k, double R_j, double R_k, double R0sq) {
    if (l_j >= 0) return log((R_k + l_k) / fmax(R_j + l_j, 1e-300));
    if (l_k <= 0) return log((R_j - l_j) / fmax(R_k - l_k, 1e-300));
    return log((R_k + l_k) * (R_j - l_j) / fmax(R0sq, 1e-300));
}

/* Solid angle and single-layer integral of a Riemann sub-triangle (corners minus the point). */
static void tri_estimate(const double a[3][3], double tol, double *psi, double *omega) {
    double e1[3], e2[3], cr[3], R[3];
    for (int c = 0; c < 3; ++c) {
        e1[c] = a[1][c] - a[0][c];
        e2[c] = a[2][c] - a[0][c];
    }
    cross3(e1, e2, cr);
    double two_area = sqrt(dot3(cr, cr));
    if (!(two_area > 0)) {
        *psi = *omega = 0.0;
        return;
    }
    for (int i = 0; i < 3; ++i) R[i] = sqrt(dot3(a[i], a[i]));
    double c12[3];
    cross3(a[1], a[2], c12);
    double det = dot3(a[0], c12); /* = h 2A, positive on the inner side */
    double den = R[0] * R[1] * R[2] + dot3(a[0], a[1]) * R[2] + dot3(a[0], a[2]) * R[1] + dot3(a[1], a[2]) * R[0];
    double h = det / two_area, dI = 0.0;
    /* A point on the plane gets the principal value (no solid angle), as in tc_tri_green. */
    double om = fabs(h) <= tol ? 0.0 : 2.0 * atan2(det, den);
    for (int e = 0; e < 3; ++e) {
        const double *pj = a[(e + 1) % 3], *pk = a[(e + 2) % 3];
        double E[3] = {pk[0] - pj[0], pk[1] - pj[1], pk[2] - pj[2]}, ell = sqrt(dot3(E, E));
        if (!(ell > 0)) continue;
        double u[3] = {E[0] / ell, E[1] / ell, E[2] / ell}, m[3];
        cross3(u, cr, m); /* outward in-plane normal times 2A */
        double d = dot3(pj, m) / two_area;
        if (d == 0) continue;
        double l_j = dot3(pj, u), l_k = dot3(pk, u);
        dI += d * edge_log(l_j, l_k, R[(e + 1) % 3], R[(e + 2) % 3], d * d + h * h);
    }
    *omega = om;
    *psi = (dI - h * om) / FOUR_PI;
}

/* Eq. 19 (m = 3): 2K + 1 nodes in [0, 1] concentrated around t. */
static void grid19(double t, int K, double *x) {
    for (int i = 0; i <= 2 * K; ++i) {
        if (i < K) {
            double s = (double)(K - i) / K;
            x[i] = (1 - s * s * s) * t;
        } else if (i > K) {
            double s = (double)(i - K) / K;
            x[i] = (t - 1) * (1 - s * s * s) + 1;
        } else {
            x[i] = t;
        }
    }
}

/*
 * P: (V, 3) vertices; quads: (Q, 4) int32; size: (Q,); pinv, null: (Q, 8, 4) pseudo-inverse and
 * null-space basis (columns) of A_q built on corners relative to origin (3,); pattern: (Pn, 3, 2)
 * int32 sub-triangles as (u index, v index) on a (2K+1)^2 grid; X: (n, 3). Outputs: PHI (n, V)
 * incremented by the quads' phi (principal values on the cage), PSIQ (n, 4Q), ONQ (n,) the first
 * quad a point lies on (or -1) and UV (n, 2) its projection there.
 */
void tc_qgc3d(const double *P, long V, const int *quads, long Q, const double *size, const double *pinv,
              const double *null, const double *origin, const int *pattern, long Pn, int K, const double *X, long n,
              double tol, int nthreads, double *PHI, double *PSIQ, int *ONQ, double *UV) {
    const int G = 2 * K + 1;
#pragma omp parallel num_threads(nthreads)
    {
        double *buf = (double *)malloc(sizeof(double) * (2 * (size_t)G + 3 * (size_t)G * G));
        double *un = buf, *vn = un + G, *S = vn + G;
#pragma omp for schedule(dynamic, 16)
        for (long pt = 0; pt < n; ++pt) {
            const double *x = X + 3 * pt;
            double *phi = PHI + pt * V, *psiq = PSIQ + pt * 4 * Q;
            ONQ[pt] = -1;
            for (long q = 0; q < Q; ++q) {
                const int *qi = quads + 4 * q;
                quad_pair qp;
                tc_quad_pair(P, qi, x, size[q], tol, &qp);
                double u = qp.u, v = qp.v;
                if (qp.on && ONQ[pt] < 0) { /* (a corner: its Lagrange values) */
                    ONQ[pt] = (int)q;
                    UV[2 * pt] = qp.vertex < 0 ? u : (qp.vertex == 1 || qp.vertex == 2 ? 1.0 : 0.0);
                    UV[2 * pt + 1] = qp.vertex < 0 ? v : (qp.vertex >= 2 ? 1.0 : 0.0);
                }
                const double *b = qp.b, *cc = qp.cc, *dd = qp.dd;
                /* Invariants on the fan from the projection to the four edges. */
                double apex[3], rhs[4] = {0, 0, 0, 0};
                for (int c = 0; c < 3; ++c) apex[c] = qp.p[0][c] + u * b[c] + v * cc[c] + u * v * dd[c];
                for (int e = 0; e < 4; ++e) {
                    double a[3][3], nf[3], ell[3], edir[9], eout[9], gbary[9], ph[3], ps, om, al[3];
                    memcpy(a[0], qp.p[e], sizeof(a[0]));
                    memcpy(a[1], qp.p[(e + 1) & 3], sizeof(a[1]));
                    memcpy(a[2], apex, sizeof(a[2]));
                    double two_area = tc_tri_frame(a, nf, ell, edir, eout, gbary);
                    tc_tri_green(a, nf, two_area, ell, edir, eout, gbary, tol, ph, &ps, &om, al);
                    for (int i = 0; i < 3; ++i) {
                        for (int c = 0; c < 3; ++c) rhs[c] += ph[i] * (a[i][c] + x[c] - origin[c]);
                        rhs[3] += ph[i];
                    }
                    for (int c = 0; c < 3; ++c) rhs[c] += ps * nf[c];
                }
                const double *Ap = pinv + 32 * q, *Nl = null + 32 * q;
                double bar[8], est[8] = {0, 0, 0, 0, 0, 0, 0, 0};
                for (int i = 0; i < 8; ++i)
                    bar[i] = Ap[4 * i] * rhs[0] + Ap[4 * i + 1] * rhs[1] + Ap[4 * i + 2] * rhs[2] + Ap[4 * i + 3] * rhs[3];
                /* Riemann estimate on the adaptive tessellation (Algorithm 1, Eqs. 17-18). */
                grid19(u, K, un);
                grid19(v, K, vn);
                for (int i = 0; i < G; ++i)
                    for (int j = 0; j < G; ++j)
                        for (int c = 0; c < 3; ++c)
                            S[3 * (i * G + j) + c] = qp.p[0][c] + un[i] * b[c] + vn[j] * cc[c] + un[i] * vn[j] * dd[c];
                for (long t = 0; t < Pn; ++t) {
                    const int *pt3 = pattern + 6 * t;
                    double a[3][3], uc = 0, vc = 0, ps, om;
                    for (int r = 0; r < 3; ++r) {
                        int iu = pt3[2 * r], iv = pt3[2 * r + 1];
                        memcpy(a[r], S + 3 * (iu * G + iv), sizeof(a[r]));
                        uc += un[iu];
                        vc += vn[iv];
                    }
                    uc /= 3;
                    vc /= 3;
                    tri_estimate(a, tol, &ps, &om);
                    double Nc[3];
                    for (int c = 0; c < 3; ++c) Nc[c] = qp.N0[c] + uc * qp.Nu[c] + vc * qp.Nv[c];
                    double Nn = sqrt(dot3(Nc, Nc)), sp = Nn > 0 ? ps / Nn : 0.0, so = om / FOUR_PI;
                    double bc[4] = {(1 - uc) * (1 - vc), uc * (1 - vc), uc * vc, (1 - uc) * vc};
                    for (int k = 0; k < 4; ++k) {
                        est[k] += bc[k] * so;
                        est[4 + k] += bc[k] * sp;
                    }
                }
                /* Phi = Phi_bar + sum_i lambda_i kappa_i with the norm correction. */
                double eb = 0, bb = 0, coef[4];
                for (int i = 0; i < 8; ++i) {
                    eb += est[i] * bar[i];
                    bb += bar[i] * bar[i];
                }
                double scale = eb != 0 ? bb / eb : 0.0;
                for (int j = 0; j < 4; ++j) {
                    coef[j] = 0;
                    for (int i = 0; i < 8; ++i) coef[j] += Nl[4 * i + j] * est[i];
                    coef[j] *= scale;
                }
                for (int i = 0; i < 8; ++i) {
                    double val = bar[i];
                    for (int j = 0; j < 4; ++j) val += Nl[4 * i + j] * coef[j];
                    if (i < 4)
                        phi[qi[i]] += val;
                    else
                        psiq[4 * q + i - 4] = val;
                }
            }
        }
        free(buf);
    }
}
