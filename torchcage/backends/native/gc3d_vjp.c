/*
 * Vector-Jacobian product of 3D Green coordinates with respect to the query points and the rest
 * cage (float64): the hand-derived reverse mode of the closed forms of
 * torchcage/families/green/kernel3d.py (triangle_integrals, whose docstring gives them) and of the
 * far-field rule (far_triangle.py), for the points whose every pair takes one of those two forms.
 *
 * Per pair, with a_i = p_i - x, u_e, m_e the unit direction and outward in-plane normal of the edge
 * opposite corner e (from corner e+1 to e+2), n the unit normal, g_i the hat gradients:
 *   h = a_0 . n, l_j = a_j . u_e, l_k = a_k . u_e, d_e = a_j . m_e,
 *   I_e = the edge integral (a log ratio, three branches as _edge_integrals),
 *   Omega = sign(h) sum_e [atan2(d_e l_k, d_e^2 + h^2 + |h| R_k) - atan2(d_e l_j, ... R_j)],
 *   alpha_i = d_i |g_i|, K = -sum_e m_e I_e,
 *   4 pi phi_i = alpha_i Omega + h g_i . K,  4 pi psi = sum_e d_e I_e - h Omega;
 * far from the face (nearest corner far_c longest edges away), with nodes y_q, weights w_q and
 * barycentric coordinates b_qi: 4 pi phi_i = h sum_q w_q b_qi / r_q^3, 4 pi psi = sum_q w_q / r_q.
 *
 * The face constants (n, u_e, m_e, g_i, |g_i|, y_q, w_q) are inputs here: their cotangents are
 * summed over the points and returned (GF, GN, GW), and the caller carries them to the vertices
 * through the few tensor operations that build them (torch autograd over T faces). The corners
 * a_i enter directly: GA (V, 3) holds their cotangents summed over the points, and
 * dL/dx = -sum of a point's corner and node cotangents (the pair depends on x through a_i and
 * y_q - x only).
 *
 * A point is regular when, for every face, the face has an area, is not thin (the caller's flag)
 * or is seen from far, and, when not seen from far, |h| >= near_c min_i R_i, |h| > tol and
 * min_i R_i >= vertex_c max_i R_i (no point on or near a face's plane or a corner: the torch
 * kernel's perpendicular forms and on-face limits). The other points get reg = 0 and a zero row,
 * and add nothing: the caller computes them.
 *
 * P (V, 3); tri (T, 3); nrm (T, 3); edir, eout, gbary (T, 3, 3) (row e: the edge opposite corner e,
 * or corner e's gradient); gnorm (T, 3) = |gbary|; two_area, longest (T,); thin (T,) 1 for thin
 * faces; far_nodes (T, Q, 3), far_w (T, Q), far_bary (Q, 3); X (n, 3); GPHI (n, V), GPSI (n, T)
 * the cotangents. Outputs: GX (n, 3), GA (V, 3), GF (T, 33) (n 3, edir 9, eout 9, gbary 9,
 * gnorm 3), GN (T, Q, 3), GW (T, Q), reg (n,).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

#define FOUR_PI 12.566370614359172953850573533118
#define GF_SIZE 33
#define GF_N 0
#define GF_EDIR 3
#define GF_EOUT 12
#define GF_GBARY 21
#define GF_GNORM 30

/* The face constants of one face, and where their cotangents go. */
typedef struct {
    const double *n, *ed, *eo, *gb, *gn; /* (3), (3, 3), (3, 3), (3, 3), (3) */
    double *gf;                          /* (GF_SIZE) cotangents */
} face_in;

static inline void axpy3(double s, const double *x, double *y) {
    y[0] += s * x[0], y[1] += s * x[1], y[2] += s * x[2];
}

/* One pair by the closed forms: a (3 corners x 3) the corners minus the point, bphi (3) and bpsi
 * the cotangents divided by 4 pi. Adds the corners' cotangents to ga and the face's to f->gf. */
static void closed_pair(const double a[3][3], const face_in *f, const double bphi[3], double bpsi, double ga[3][3]) {
    double R[3], lj[3], lk[3], d[3], I[3], R0c[3] = {0, 0, 0}, w[3][3] = {{0}};
    int br[3];
    for (int i = 0; i < 3; ++i) R[i] = sqrt(dot3(a[i], a[i]));
    const double h = dot3(a[0], f->n), sg = h >= 0 ? 1.0 : -1.0, ha = sg * h;
    for (int e = 0; e < 3; ++e) {
        const int j = (e + 1) % 3, k = (e + 2) % 3;
        const double *u = f->ed + 3 * e;
        lj[e] = dot3(a[j], u), lk[e] = dot3(a[k], u), d[e] = dot3(a[j], f->eo + 3 * e);
        if (lj[e] >= 0) {
            br[e] = 0, I[e] = log((R[k] + lk[e]) / (R[j] + lj[e]));
        } else if (lk[e] <= 0) {
            br[e] = 1, I[e] = log((R[j] - lj[e]) / (R[k] - lk[e]));
        } else {
            cross3(a[j], u, w[e]);
            R0c[e] = dot3(w[e], w[e]);
            br[e] = 2, I[e] = log((R[k] + lk[e]) * (R[j] - lj[e]) / R0c[e]);
        }
    }
    double xk[3], yk[3], xj[3], yj[3], omega = 0.0;
    for (int e = 0; e < 3; ++e) {
        const int j = (e + 1) % 3, k = (e + 2) % 3;
        const double r0 = d[e] * d[e] + ha * ha;
        xk[e] = r0 + ha * R[k], yk[e] = d[e] * lk[e], xj[e] = r0 + ha * R[j], yj[e] = d[e] * lj[e];
        omega += atan2(yk[e], xk[e]) - atan2(yj[e], xj[e]);
    }
    omega *= sg;
    double K[3] = {0, 0, 0}, gK[3], alpha[3];
    for (int e = 0; e < 3; ++e) axpy3(-I[e], f->eo + 3 * e, K);
    for (int i = 0; i < 3; ++i) gK[i] = dot3(f->gb + 3 * i, K), alpha[i] = d[i] * f->gn[i];
    /* reverse */
    double b_omega = -bpsi * h, b_h = -bpsi * omega, kbar[3] = {0, 0, 0}, b_d[3], b_I[3];
    for (int i = 0; i < 3; ++i) {
        b_omega += bphi[i] * alpha[i];
        b_h += bphi[i] * gK[i];
        axpy3(bphi[i] * h, f->gb + 3 * i, kbar);
        axpy3(bphi[i] * h, K, f->gf + GF_GBARY + 3 * i);
        f->gf[GF_GNORM + i] += bphi[i] * omega * d[i];
        b_d[i] = bpsi * I[i] + bphi[i] * omega * f->gn[i];
    }
    for (int e = 0; e < 3; ++e) {
        b_I[e] = bpsi * d[e] - dot3(kbar, f->eo + 3 * e);
        axpy3(-I[e], kbar, f->gf + GF_EOUT + 3 * e);
    }
    const double b_beta = sg * b_omega;
    double b_ha = 0.0, b_R[3] = {0, 0, 0}, b_lj[3], b_lk[3];
    for (int e = 0; e < 3; ++e) {
        const int j = (e + 1) % 3, k = (e + 2) % 3;
        const double dk = b_beta / (xk[e] * xk[e] + yk[e] * yk[e]), dj = b_beta / (xj[e] * xj[e] + yj[e] * yj[e]);
        const double b_yk = dk * xk[e], b_xk = -dk * yk[e], b_yj = -dj * xj[e], b_xj = dj * yj[e];
        const double b_r0 = b_xk + b_xj;
        b_d[e] += b_yk * lk[e] + b_yj * lj[e] + 2.0 * d[e] * b_r0;
        b_lk[e] = b_yk * d[e], b_lj[e] = b_yj * d[e];
        b_ha += b_xk * R[k] + b_xj * R[j] + 2.0 * ha * b_r0;
        b_R[k] += b_xk * ha, b_R[j] += b_xj * ha;
    }
    b_h += sg * b_ha;
    for (int e = 0; e < 3; ++e) {
        const int j = (e + 1) % 3, k = (e + 2) % 3;
        const double *u = f->ed + 3 * e, *m = f->eo + 3 * e;
        double *gu = f->gf + GF_EDIR + 3 * e;
        if (br[e] == 0) {
            const double t1 = b_I[e] / (R[k] + lk[e]), t2 = b_I[e] / (R[j] + lj[e]);
            b_R[k] += t1, b_lk[e] += t1, b_R[j] -= t2, b_lj[e] -= t2;
        } else if (br[e] == 1) {
            const double t1 = b_I[e] / (R[j] - lj[e]), t2 = b_I[e] / (R[k] - lk[e]);
            b_R[j] += t1, b_lj[e] -= t1, b_R[k] -= t2, b_lk[e] += t2;
        } else {
            const double t1 = b_I[e] / (R[k] + lk[e]), t2 = b_I[e] / (R[j] - lj[e]), s = -2.0 * b_I[e] / R0c[e];
            b_R[k] += t1, b_lk[e] += t1, b_R[j] += t2, b_lj[e] -= t2;
            double bw[3] = {s * w[e][0], s * w[e][1], s * w[e][2]}, c[3];
            cross3(u, bw, c); /* w = a_j x u */
            axpy3(1.0, c, ga[j]);
            cross3(bw, a[j], c);
            axpy3(1.0, c, gu);
        }
        axpy3(b_lj[e], u, ga[j]);
        axpy3(b_lj[e], a[j], gu);
        axpy3(b_lk[e], u, ga[k]);
        axpy3(b_lk[e], a[k], gu);
        axpy3(b_d[e], m, ga[j]);
        axpy3(b_d[e], a[j], f->gf + GF_EOUT + 3 * e);
    }
    for (int i = 0; i < 3; ++i) axpy3(b_R[i] / R[i], a[i], ga[i]);
    axpy3(b_h, f->n, ga[0]);
    axpy3(b_h, a[0], f->gf + GF_N);
}

/* One pair by the far-field rule: x the point, a0 = p_0 - x, the face's Q nodes (Q, 3), weights
 * (Q,) and the rule's barycentric coordinates (Q, 3); bphi, bpsi as closed_pair. Adds to ga0 (the
 * first corner's cotangent, through h), gx (the point's, through the nodes' offsets), the face's
 * normal cotangent (gfn) and its nodes' (gn) and weights' (gw). */
static void far_pair(const double *x, const double *a0, const double *n, const double *nodes, const double *wq,
                     const double *bary, long Q, const double bphi[3], double bpsi, double *ga0, double *gx,
                     double *gfn, double *gn, double *gw) {
    const double h = dot3(a0, n);
    double b_h = 0.0;
    for (long q = 0; q < Q; ++q) {
        const double *b = bary + 3 * q, *y = nodes + 3 * q;
        const double aq[3] = {y[0] - x[0], y[1] - x[1], y[2] - x[2]};
        const double ir = 1.0 / sqrt(dot3(aq, aq)), w1 = wq[q] * ir, w3 = w1 * ir * ir;
        const double sb = bphi[0] * b[0] + bphi[1] * b[1] + bphi[2] * b[2], c = h * sb;
        b_h += sb * w3;
        const double s = -(3.0 * c * w3 + bpsi * w1) * ir * ir; /* d(w r^-3) = -3 w r^-5 a, d(w/r) = -w r^-3 a */
        axpy3(s, aq, gn + 3 * q);
        axpy3(-s, aq, gx);
        gw[q] += c * ir * ir * ir + bpsi * ir;
    }
    axpy3(b_h, n, ga0);
    axpy3(b_h, a0, gfn);
}

/* 1 when every pair of the point x takes the closed forms or the far-field rule (see the top). */
static int regular_point(const double *P, const int *tri, long T, const double *nrm, const double *two_area,
                         const double *longest, const unsigned char *thin, const double *x, double far_c,
                         double near_c, double vertex_c, double tol) {
    for (long f = 0; f < T; ++f) {
        if (!(two_area[f] > 0)) return 0;
        const int *t = tri + 3 * f;
        double a[3][3], r2[3];
        for (int c = 0; c < 3; ++c) {
            for (int k = 0; k < 3; ++k) a[c][k] = P[3 * t[c] + k] - x[k];
            r2[c] = dot3(a[c], a[c]);
        }
        const double rmin2 = fmin(fmin(r2[0], r2[1]), r2[2]), rmax2 = fmax(fmax(r2[0], r2[1]), r2[2]);
        const double far = far_c * longest[f];
        if (longest[f] > 0 && rmin2 >= far * far) continue;
        if (thin[f]) return 0;
        const double h = fabs(dot3(a[0], nrm + 3 * f)), rmin = sqrt(rmin2);
        if (!(h >= near_c * rmin) || !(h > tol) || !(rmin >= vertex_c * sqrt(rmax2))) return 0;
    }
    return 1;
}

void tc_gc3d_vjp(const double *P, long V, const int *tri, long T, const double *nrm, const double *edir,
                 const double *eout, const double *gbary, const double *gnorm, const double *two_area,
                 const double *longest, const unsigned char *thin, const double *far_nodes, const double *far_w,
                 const double *far_bary, long Q, double far_c, double near_c, double vertex_c, double tol,
                 const double *X, long n, const double *GPHI, const double *GPSI, int nthreads, double *GX,
                 double *GA, double *GF, double *GN, double *GW, unsigned char *reg) {
    memset(GA, 0, sizeof(double) * 3 * (size_t)V);
    memset(GF, 0, sizeof(double) * GF_SIZE * (size_t)T);
    memset(GN, 0, sizeof(double) * 3 * (size_t)(T * Q));
    memset(GW, 0, sizeof(double) * (size_t)(T * Q));
#pragma omp parallel num_threads(nthreads)
    {
        /* this thread's sums: corners (V, 3), face constants (T, GF_SIZE), nodes (T, Q, 3), weights (T, Q) */
        const size_t size = 3 * (size_t)V + GF_SIZE * (size_t)T + 4 * (size_t)(T * Q);
        double *ws = (double *)calloc(size > 0 ? size : 1, sizeof(double));
        double *ga_t = ws, *gf_t = ws + 3 * V, *gn_t = gf_t + GF_SIZE * T, *gw_t = gn_t + 3 * T * Q;
#pragma omp for schedule(dynamic, 16)
        for (long i = 0; i < n; ++i) {
            const double *x = X + 3 * i;
            double *gx = GX + 3 * i;
            gx[0] = gx[1] = gx[2] = 0.0;
            reg[i] = ws != NULL &&
                     regular_point(P, tri, T, nrm, two_area, longest, thin, x, far_c, near_c, vertex_c, tol);
            if (!reg[i]) continue; /* (no scratch: left to the caller too) */
            const double *gphi = GPHI + V * i, *gpsi = GPSI + T * i;
            for (long f = 0; f < T; ++f) {
                const int *t = tri + 3 * f;
                const double bphi[3] = {gphi[t[0]] / FOUR_PI, gphi[t[1]] / FOUR_PI, gphi[t[2]] / FOUR_PI};
                const double bpsi = gpsi[f] / FOUR_PI;
                if (bphi[0] == 0 && bphi[1] == 0 && bphi[2] == 0 && bpsi == 0) continue;
                double a[3][3], ga[3][3] = {{0}}, rmin2 = INFINITY;
                for (int c = 0; c < 3; ++c) {
                    for (int k = 0; k < 3; ++k) a[c][k] = P[3 * t[c] + k] - x[k];
                    rmin2 = fmin(rmin2, dot3(a[c], a[c]));
                }
                const double far = far_c * longest[f];
                if (longest[f] > 0 && rmin2 >= far * far) {
                    far_pair(x, a[0], nrm + 3 * f, far_nodes + 3 * Q * f, far_w + Q * f, far_bary, Q, bphi, bpsi,
                             ga[0], gx, gf_t + GF_SIZE * f + GF_N, gn_t + 3 * Q * f, gw_t + Q * f);
                } else {
                    const face_in fi = {nrm + 3 * f, edir + 9 * f, eout + 9 * f, gbary + 9 * f, gnorm + 3 * f,
                                        gf_t + GF_SIZE * f};
                    closed_pair(a, &fi, bphi, bpsi, ga);
                }
                for (int c = 0; c < 3; ++c)
                    for (int k = 0; k < 3; ++k) ga_t[3 * t[c] + k] += ga[c][k], gx[k] -= ga[c][k];
            }
        }
        if (ws != NULL) {
#pragma omp critical
            {
                for (size_t k = 0; k < 3 * (size_t)V; ++k) GA[k] += ga_t[k];
                for (size_t k = 0; k < GF_SIZE * (size_t)T; ++k) GF[k] += gf_t[k];
                for (size_t k = 0; k < 3 * (size_t)(T * Q); ++k) GN[k] += gn_t[k];
                for (size_t k = 0; k < (size_t)(T * Q); ++k) GW[k] += gw_t[k];
            }
        }
        free(ws);
    }
}
