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

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector log and atan2 (libmvec) in the plain loops below. */
__attribute__((simd("notinbranch"))) double log(double);
__attribute__((simd("notinbranch"))) double atan2(double, double);
#endif

#define FOUR_PI 12.566370614359172953850573533118

/* int_e dl / r along an edge (as edge_integral in gc3d.c, without the stored constants). */
static inline double edge_log(double l_j, double l_k, double R_j, double R_k, double R0sq) {
    if (l_j >= 0) return log((R_k + l_k) / fmax(R_j + l_j, 1e-300));
    if (l_k <= 0) return log((R_j - l_j) / fmax(R_k - l_k, 1e-300));
    return log((R_k + l_k) * (R_j - l_j) / fmax(R0sq, 1e-300));
}

/* For the edge from aj to ak of a sub-triangle with normal cr (length 2A, inv2A its inverse), at
 * distance h from its plane: the signed distance d of the foot point to the edge line and the
 * argument of the log in int_e dl / r (as edge_integral in gc3d.c). */
static inline void edge_arg(double ajx, double ajy, double ajz, double akx, double aky, double akz, double Rj,
                            double Rk, double crx, double cry, double crz, double inv2A, double h, double *d_out,
                            double *arg_out) {
    double Ex = akx - ajx, Ey = aky - ajy, Ez = akz - ajz;
    double ell = sqrt(Ex * Ex + Ey * Ey + Ez * Ez), invl = ell > 0 ? 1.0 / ell : 0.0;
    double ux = Ex * invl, uy = Ey * invl, uz = Ez * invl;
    double mx = uy * crz - uz * cry, my = uz * crx - ux * crz, mz = ux * cry - uy * crx; /* outward x 2A */
    double d = (ajx * mx + ajy * my + ajz * mz) * inv2A;
    double lj = ajx * ux + ajy * uy + ajz * uz, lk = akx * ux + aky * uy + akz * uz, R0sq = d * d + h * h;
    double arg;
    if (lj >= 0)
        arg = (Rk + lk) / fmax(Rj + lj, 1e-300);
    else if (lk <= 0)
        arg = (Rj - lj) / fmax(Rk - lk, 1e-300);
    else
        arg = (Rk + lk) * (Rj - lj) / fmax(R0sq, 1e-300);
    *d_out = d;
    *arg_out = fmax(arg, 1e-300);
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
        double *buf = (double *)malloc(sizeof(double) * (2 * (size_t)G + 4 * (size_t)G * G + 10 * (size_t)Pn));
        double *un = buf, *vn = un + G, *Sx = vn + G, *Sy = Sx + G * G, *Sz = Sy + G * G, *SR = Sz + G * G;
        double *TH = SR + G * G, *TA = TH + Pn, *TDET = TA + Pn, *TDEN = TDET + Pn, *TD = TDEN + Pn, *TL = TD + 3 * Pn;
        /* Sub-triangle corners as flat grid-node indices, and their u and v indices. */
        int *node = (int *)malloc(sizeof(int) * 9 * (size_t)Pn), *iu = node + 3 * Pn, *iv = iu + 3 * Pn;
        for (long t = 0; t < 3 * Pn; ++t) {
            iu[t] = pattern[2 * t];
            iv[t] = pattern[2 * t + 1];
            node[t] = iu[t] * G + iv[t];
        }
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
                /* Outside the quad's tetrahedron the point cannot lie between the sheet and the split
                 * (q0 q1 q2), (q0 q2 q3): those two triangles give the same invariants more cheaply. */
                int split = !qp.inside && !qp.on;
                for (int e = 0; e < (split ? 2 : 4); ++e) {
                    double a[3][3], nf[3], ell[3], edir[9], eout[9], gbary[9], ph[3], ps, om, al[3];
                    if (split) {
                        memcpy(a[0], qp.p[0], sizeof(a[0]));
                        memcpy(a[1], qp.p[e + 1], sizeof(a[1]));
                        memcpy(a[2], qp.p[e + 2], sizeof(a[2]));
                    } else {
                        memcpy(a[0], qp.p[e], sizeof(a[0]));
                        memcpy(a[1], qp.p[(e + 1) & 3], sizeof(a[1]));
                        memcpy(a[2], apex, sizeof(a[2]));
                    }
                    double two_area = tc_tri_frame(a, nf, ell, edir, eout, gbary);
                    tc_tri_green(a, nf, two_area, ell, edir, eout, gbary, tol, ph, &ps, &om, al);
                    for (int i = 0; i < 3; ++i) {
                        for (int c = 0; c < 3; ++c) rhs[c] += ph[i] * (a[i][c] + x[c] - origin[c]);
                        rhs[3] += ph[i];
                    }
                    for (int c = 0; c < 3; ++c) rhs[c] += ps * nf[c];
                }
                const double *Ap = pinv + 32 * q, *Nl = null + 32 * q;
                double bar[8];
                for (int i = 0; i < 8; ++i)
                    bar[i] = Ap[4 * i] * rhs[0] + Ap[4 * i + 1] * rhs[1] + Ap[4 * i + 2] * rhs[2] + Ap[4 * i + 3] * rhs[3];
                /* Riemann estimate on the adaptive tessellation (Algorithm 1, Eqs. 17-18). */
                grid19(u, K, un);
                grid19(v, K, vn);
                for (int i = 0; i < G; ++i)
                    for (int j = 0; j < G; ++j) {
                        int g = i * G + j;
                        Sx[g] = qp.p[0][0] + un[i] * b[0] + vn[j] * cc[0] + un[i] * vn[j] * dd[0];
                        Sy[g] = qp.p[0][1] + un[i] * b[1] + vn[j] * cc[1] + un[i] * vn[j] * dd[1];
                        Sz[g] = qp.p[0][2] + un[i] * b[2] + vn[j] * cc[2] + un[i] * vn[j] * dd[2];
                        SR[g] = sqrt(Sx[g] * Sx[g] + Sy[g] * Sy[g] + Sz[g] * Sz[g]);
                    }
                const double *N0 = qp.N0, *Nu = qp.Nu, *Nv = qp.Nv;
                /* Sub-triangles in three passes: geometry and the arguments of the logs and atan2s,
                 * then the logs and atan2s in plain loops (vectorised with libmvec), then the sums. */
                for (long t = 0; t < Pn; ++t) {
                    int i0 = node[3 * t], i1 = node[3 * t + 1], i2 = node[3 * t + 2];
                    double a0x = Sx[i0], a0y = Sy[i0], a0z = Sz[i0], R0 = SR[i0];
                    double a1x = Sx[i1], a1y = Sy[i1], a1z = Sz[i1], R1 = SR[i1];
                    double a2x = Sx[i2], a2y = Sy[i2], a2z = Sz[i2], R2 = SR[i2];
                    double f1x = a1x - a0x, f1y = a1y - a0y, f1z = a1z - a0z;
                    double f2x = a2x - a0x, f2y = a2y - a0y, f2z = a2z - a0z;
                    double crx = f1y * f2z - f1z * f2y, cry = f1z * f2x - f1x * f2z, crz = f1x * f2y - f1y * f2x;
                    double two_area = sqrt(crx * crx + cry * cry + crz * crz);
                    double inv2A = two_area > 0 ? 1.0 / two_area : 0.0;
                    /* Van Oosterom-Strackee: tan(omega / 2) = det / den; det = h 2A. */
                    double det = a0x * (a1y * a2z - a1z * a2y) + a0y * (a1z * a2x - a1x * a2z) + a0z * (a1x * a2y - a1y * a2x);
                    double h = det * inv2A;
                    TH[t] = h;
                    TA[t] = two_area;
                    TDET[t] = det;
                    TDEN[t] = R0 * R1 * R2 + (a0x * a1x + a0y * a1y + a0z * a1z) * R2 +
                              (a0x * a2x + a0y * a2y + a0z * a2z) * R1 + (a1x * a2x + a1y * a2y + a1z * a2z) * R0;
                    edge_arg(a1x, a1y, a1z, a2x, a2y, a2z, R1, R2, crx, cry, crz, inv2A, h, TD + 3 * t, TL + 3 * t);
                    edge_arg(a2x, a2y, a2z, a0x, a0y, a0z, R2, R0, crx, cry, crz, inv2A, h, TD + 3 * t + 1, TL + 3 * t + 1);
                    edge_arg(a0x, a0y, a0z, a1x, a1y, a1z, R0, R1, crx, cry, crz, inv2A, h, TD + 3 * t + 2, TL + 3 * t + 2);
                }
#pragma omp simd
                for (long i = 0; i < 3 * Pn; ++i) TL[i] = log(TL[i]);
#pragma omp simd
                for (long t = 0; t < Pn; ++t) TDET[t] = 2.0 * atan2(TDET[t], TDEN[t]);
                double e0 = 0, e1 = 0, e2 = 0, e3 = 0, e4 = 0, e5 = 0, e6 = 0, e7 = 0;
                for (long t = 0; t < Pn; ++t) {
                    double h = TH[t], two_area = TA[t];
                    double om = (fabs(h) <= tol || two_area == 0) ? 0.0 : TDET[t];
                    double dI = 0.0;
                    for (int e = 0; e < 3; ++e) {
                        double d = TD[3 * t + e];
                        dI += d != 0 ? d * TL[3 * t + e] : 0.0;
                    }
                    double ps = two_area > 0 ? (dI - h * om) / FOUR_PI : 0.0;
                    double uc = (un[iu[3 * t]] + un[iu[3 * t + 1]] + un[iu[3 * t + 2]]) / 3;
                    double vc = (vn[iv[3 * t]] + vn[iv[3 * t + 1]] + vn[iv[3 * t + 2]]) / 3;
                    double Ncx = N0[0] + uc * Nu[0] + vc * Nv[0], Ncy = N0[1] + uc * Nu[1] + vc * Nv[1];
                    double Ncz = N0[2] + uc * Nu[2] + vc * Nv[2], Nn = sqrt(Ncx * Ncx + Ncy * Ncy + Ncz * Ncz);
                    double sp = Nn > 0 ? ps / Nn : 0.0, so = om / FOUR_PI;
                    double b0 = (1 - uc) * (1 - vc), b1 = uc * (1 - vc), b2 = uc * vc, b3 = (1 - uc) * vc;
                    e0 += b0 * so;
                    e1 += b1 * so;
                    e2 += b2 * so;
                    e3 += b3 * so;
                    e4 += b0 * sp;
                    e5 += b1 * sp;
                    e6 += b2 * sp;
                    e7 += b3 * sp;
                }
                double est[8] = {e0, e1, e2, e3, e4, e5, e6, e7};
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
        free(node);
    }
}
