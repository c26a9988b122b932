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
 * tc_gc3d_vjp_batch takes B cages with one topology; per cage: P (V, 3); nrm (T, 3); edir, eout,
 * gbary (T, 3, 3) (row e: the edge opposite corner e, or corner e's gradient); gnorm (T, 3) =
 * |gbary|; two_area, longest (T,); thin (T,) 1 for thin faces; far_nodes (T, Q, 3), far_w (T, Q);
 * tol; X (n, 3); GPHI (n, V), GPSI (n, T) the cotangents. Shared: tri (T, 3), far_bary (Q, 3).
 * Outputs per cage: GX (n, 3), GA (V, 3), GF (T, 33) (n 3, edir 9, eout 9, gbary 9, gnorm 3),
 * GN (T, Q, 3), GW (T, Q), reg (n,).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector log and atan2 (libmvec) in the lane loop below. */
__attribute__((simd("notinbranch"))) double log(double);
__attribute__((simd("notinbranch"))) double atan2(double, double);
#endif

#define FOUR_PI 12.566370614359172953850573533118
#define GF_SIZE 33
#define GF_N 0
#define GF_EDIR 3
#define GF_EOUT 12
#define GF_GBARY 21
#define GF_GNORM 30

/* The face constants of one face: n (3), edir, eout, gbary (3, 3), gnorm (3). */
typedef struct {
    const double *n, *ed, *eo, *gb, *gn;
} face_in;

static inline void axpy3(double s, const double *x, double *y) {
    y[0] += s * x[0], y[1] += s * x[1], y[2] += s * x[2];
}

/* One pair by the far-field rule: x the point, a0 = p_0 - x, the face's Q nodes (Q, 3), weights
 * (Q,) and the rule's barycentric coordinates (Q, 3); bphi (3), bpsi the cotangents over 4 pi. Adds to ga0 (the
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

#ifndef GC_VJP_LANES
#define GC_VJP_LANES 4 /* points side by side (one AVX2 register of doubles) */
#endif
#define VL GC_VJP_LANES

/* a_j . v and the components of a_j x v, a_j given as the variables a<j>x, a<j>y, a<j>z */
#define DOTA(j, v) (a##j##x * (v)[0] + a##j##y * (v)[1] + a##j##z * (v)[2])

/* Edge e (from corner j to corner k) of closed_lanes' forward pass: l_j, l_k, d_e, the edge integral
 * I_e = log(num_e / den_e) (one branch of three, as kernel3d._edge_integrals), the solid angle's term be_e. */
#define EDGE_FWD(e, j, k)                                                                                            \
    const double *u##e = f->ed + 3 * e, *m##e = f->eo + 3 * e;                                                      \
    double lj##e = DOTA(j, u##e), lk##e = DOTA(k, u##e), d##e = DOTA(j, m##e);                                      \
    double wx##e = a##j##y * u##e[2] - a##j##z * u##e[1], wy##e = a##j##z * u##e[0] - a##j##x * u##e[2];            \
    double wz##e = a##j##x * u##e[1] - a##j##y * u##e[0];                                                           \
    int ah##e = lj##e >= 0, bh##e = !ah##e && lk##e <= 0;                                                           \
    double num##e = ah##e ? R##k + lk##e : (bh##e ? R##j - lj##e : (R##k + lk##e) * (R##j - lj##e));                \
    double den##e = ah##e ? R##j + lj##e : (bh##e ? R##k - lk##e : wx##e * wx##e + wy##e * wy##e + wz##e * wz##e);  \
    double I##e = log(num##e / den##e);                                                                             \
    double r0##e = d##e * d##e + ha * ha;                                                                           \
    double xk##e = r0##e + ha * R##k, yk##e = d##e * lk##e, xj##e = r0##e + ha * R##j, yj##e = d##e * lj##e;        \
    double be##e = atan2(yk##e, xk##e) - atan2(yj##e, xj##e);

/* Edge e's reverse pass through the solid angle's term. */
#define EDGE_REV_OMEGA(e, j, k)                                                                                      \
    double dk##e = bbeta / (xk##e * xk##e + yk##e * yk##e), dj##e = bbeta / (xj##e * xj##e + yj##e * yj##e);        \
    double bxk##e = -dk##e * yk##e, bxj##e = dj##e * yj##e, br0##e = bxk##e + bxj##e;                               \
    bd##e += dk##e * xk##e * lk##e - dj##e * xj##e * lj##e + 2.0 * d##e * br0##e;                                   \
    double blk##e = dk##e * xk##e * d##e, blj##e = -dj##e * xj##e * d##e;                                           \
    bha += bxk##e * R##k + bxj##e * R##j + 2.0 * ha * br0##e;                                                       \
    bR##k += bxk##e * ha, bR##j += bxj##e * ha;

/* Edge e's reverse pass through its integral, l_j, l_k, d_e: the corners' and the edge's
 * constants' cotangents (gu: the direction's, go: the normal's, 3 lanes-wide rows each). */
#define EDGE_REV_EDGE(e, j, k)                                                                                       \
    {                                                                                                                \
        const double bnum = bI##e / num##e, bden = -bI##e / den##e;                                                 \
        const int st = !ah##e && !bh##e;                                                                             \
        bR##k += ah##e ? bnum : (bh##e ? bden : bnum * (R##j - lj##e));                                             \
        blk##e += ah##e ? bnum : (bh##e ? -bden : bnum * (R##j - lj##e));                                           \
        bR##j += ah##e ? bden : (bh##e ? bnum : bnum * (R##k + lk##e));                                             \
        blj##e += ah##e ? bden : (bh##e ? -bnum : -bnum * (R##k + lk##e));                                          \
        const double sw = st ? 2.0 * bden : 0.0; /* w = a_j x u, den = |w|^2 */                                    \
        const double bwx = sw * wx##e, bwy = sw * wy##e, bwz = sw * wz##e;                                           \
        ga##j##x += blj##e * u##e[0] + bd##e * m##e[0] + u##e[1] * bwz - u##e[2] * bwy;                              \
        ga##j##y += blj##e * u##e[1] + bd##e * m##e[1] + u##e[2] * bwx - u##e[0] * bwz;                              \
        ga##j##z += blj##e * u##e[2] + bd##e * m##e[2] + u##e[0] * bwy - u##e[1] * bwx;                              \
        ga##k##x += blk##e * u##e[0], ga##k##y += blk##e * u##e[1], ga##k##z += blk##e * u##e[2];                    \
        double *gu = GF + (GF_EDIR + 3 * e) * VL, *go = GF + (GF_EOUT + 3 * e) * VL;                                \
        gu[l] = ok[l] ? blj##e * a##j##x + blk##e * a##k##x + bwy * a##j##z - bwz * a##j##y : 0.0;                    \
        gu[VL + l] = ok[l] ? blj##e * a##j##y + blk##e * a##k##y + bwz * a##j##x - bwx * a##j##z : 0.0;               \
        gu[2 * VL + l] = ok[l] ? blj##e * a##j##z + blk##e * a##k##z + bwx * a##j##y - bwy * a##j##x : 0.0;           \
        go[l] = ok[l] ? bd##e * a##j##x - bI##e##kx : 0.0;                                                            \
        go[VL + l] = ok[l] ? bd##e * a##j##y - bI##e##ky : 0.0;                                                       \
        go[2 * VL + l] = ok[l] ? bd##e * a##j##z - bI##e##kz : 0.0;                                                   \
    }

/* One face by the closed forms for VL points side by side (one face; corners q0, q1, q2; points x0, x1, x2 (VL),
 * cotangents over 4 pi bp0, bp1, bp2, bps (VL)), lane by lane added to: c0, c1, c2 (3, VL) the
 * corners' cotangents, FL (GF_SIZE, VL) the face constants', gx (3, VL) the points'. Lanes with
 * ok = 0 add nothing (a select: their values may be inf or NaN). */
/* (not inlined: inlined into the point loop, gcc no longer vectorised its lane loop) */
__attribute__((noinline)) static void closed_lanes(const double *q0, const double *q1, const double *q2, const face_in *f, const double *x0,
                         const double *x1, const double *x2, const double *bp0, const double *bp1, const double *bp2,
                         const double *bps, const double *ok, double *c0, double *c1, double *c2, double *FL,
                         double *gx, double *restrict GA, double *restrict GF) {
    const double *nv = f->n, *g0 = f->gb, *g1 = f->gb + 3, *g2 = f->gb + 6, *gn = f->gn;
#pragma omp simd
    for (int l = 0; l < VL; ++l) {
        double a0x = q0[0] - x0[l], a0y = q0[1] - x1[l], a0z = q0[2] - x2[l];
        double a1x = q1[0] - x0[l], a1y = q1[1] - x1[l], a1z = q1[2] - x2[l];
        double a2x = q2[0] - x0[l], a2y = q2[1] - x1[l], a2z = q2[2] - x2[l];
        double R0 = sqrt(a0x * a0x + a0y * a0y + a0z * a0z), R1 = sqrt(a1x * a1x + a1y * a1y + a1z * a1z);
        double R2 = sqrt(a2x * a2x + a2y * a2y + a2z * a2z);
        double h = DOTA(0, nv), sg = h >= 0 ? 1.0 : -1.0, ha = sg * h;
        EDGE_FWD(0, 1, 2)
        EDGE_FWD(1, 2, 0)
        EDGE_FWD(2, 0, 1)
        double omega = sg * (be0 + be1 + be2);
        double Kx = -(m0[0] * I0 + m1[0] * I1 + m2[0] * I2), Ky = -(m0[1] * I0 + m1[1] * I1 + m2[1] * I2);
        double Kz = -(m0[2] * I0 + m1[2] * I1 + m2[2] * I2);
        double gK0 = g0[0] * Kx + g0[1] * Ky + g0[2] * Kz, gK1 = g1[0] * Kx + g1[1] * Ky + g1[2] * Kz;
        double gK2 = g2[0] * Kx + g2[1] * Ky + g2[2] * Kz;
        double p0 = bp0[l], p1 = bp1[l], p2 = bp2[l], ps = bps[l];
        /* reverse */
        double bomega = -ps * h + p0 * d0 * gn[0] + p1 * d1 * gn[1] + p2 * d2 * gn[2];
        double bh = -ps * omega + p0 * gK0 + p1 * gK1 + p2 * gK2;
        double kbx = h * (p0 * g0[0] + p1 * g1[0] + p2 * g2[0]), kby = h * (p0 * g0[1] + p1 * g1[1] + p2 * g2[1]);
        double kbz = h * (p0 * g0[2] + p1 * g1[2] + p2 * g2[2]);
        double *gg = GF + GF_GBARY * VL;
        gg[0 * VL + l] = ok[l] ? p0 * h * Kx : 0.0, gg[1 * VL + l] = ok[l] ? p0 * h * Ky : 0.0;
        gg[2 * VL + l] = ok[l] ? p0 * h * Kz : 0.0, gg[3 * VL + l] = ok[l] ? p1 * h * Kx : 0.0;
        gg[4 * VL + l] = ok[l] ? p1 * h * Ky : 0.0, gg[5 * VL + l] = ok[l] ? p1 * h * Kz : 0.0;
        gg[6 * VL + l] = ok[l] ? p2 * h * Kx : 0.0, gg[7 * VL + l] = ok[l] ? p2 * h * Ky : 0.0;
        gg[8 * VL + l] = ok[l] ? p2 * h * Kz : 0.0;
        GF[(GF_GNORM + 0) * VL + l] = ok[l] ? p0 * omega * d0 : 0.0;
        GF[(GF_GNORM + 1) * VL + l] = ok[l] ? p1 * omega * d1 : 0.0;
        GF[(GF_GNORM + 2) * VL + l] = ok[l] ? p2 * omega * d2 : 0.0;
        double bd0 = ps * I0 + p0 * omega * gn[0], bd1 = ps * I1 + p1 * omega * gn[1];
        double bd2 = ps * I2 + p2 * omega * gn[2];
        double bI0 = ps * d0 - (kbx * m0[0] + kby * m0[1] + kbz * m0[2]);
        double bI1 = ps * d1 - (kbx * m1[0] + kby * m1[1] + kbz * m1[2]);
        double bI2 = ps * d2 - (kbx * m2[0] + kby * m2[1] + kbz * m2[2]);
        double bI0kx = I0 * kbx, bI0ky = I0 * kby, bI0kz = I0 * kbz, bI1kx = I1 * kbx, bI1ky = I1 * kby;
        double bI1kz = I1 * kbz, bI2kx = I2 * kbx, bI2ky = I2 * kby, bI2kz = I2 * kbz;
        double bbeta = sg * bomega, bha = 0.0, bR0 = 0.0, bR1 = 0.0, bR2 = 0.0;
        EDGE_REV_OMEGA(0, 1, 2)
        EDGE_REV_OMEGA(1, 2, 0)
        EDGE_REV_OMEGA(2, 0, 1)
        bh += sg * bha;
        double ga0x = 0.0, ga0y = 0.0, ga0z = 0.0, ga1x = 0.0, ga1y = 0.0, ga1z = 0.0;
        double ga2x = 0.0, ga2y = 0.0, ga2z = 0.0;
        EDGE_REV_EDGE(0, 1, 2)
        EDGE_REV_EDGE(1, 2, 0)
        EDGE_REV_EDGE(2, 0, 1)
        double s0 = bR0 / R0, s1 = bR1 / R1, s2 = bR2 / R2;
        ga0x += s0 * a0x + bh * nv[0], ga0y += s0 * a0y + bh * nv[1], ga0z += s0 * a0z + bh * nv[2];
        ga1x += s1 * a1x, ga1y += s1 * a1y, ga1z += s1 * a1z;
        ga2x += s2 * a2x, ga2y += s2 * a2y, ga2z += s2 * a2z;
        GF[(GF_N + 0) * VL + l] = ok[l] ? bh * a0x : 0.0;
        GF[(GF_N + 1) * VL + l] = ok[l] ? bh * a0y : 0.0;
        GF[(GF_N + 2) * VL + l] = ok[l] ? bh * a0z : 0.0;
        GA[0 * VL + l] = ok[l] ? ga0x : 0.0, GA[1 * VL + l] = ok[l] ? ga0y : 0.0, GA[2 * VL + l] = ok[l] ? ga0z : 0.0;
        GA[3 * VL + l] = ok[l] ? ga1x : 0.0, GA[4 * VL + l] = ok[l] ? ga1y : 0.0, GA[5 * VL + l] = ok[l] ? ga1z : 0.0;
        GA[6 * VL + l] = ok[l] ? ga2x : 0.0, GA[7 * VL + l] = ok[l] ? ga2y : 0.0, GA[8 * VL + l] = ok[l] ? ga2z : 0.0;
    }
    /* (added here, not in the loop above: plain stores there keep it simple to vectorise) */
    for (int c = 0; c < 3; ++c) {
        double *cc = c == 0 ? c0 : (c == 1 ? c1 : c2);
        for (int k = 0; k < 3 * VL; ++k) cc[k] += GA[3 * VL * c + k], gx[k] -= GA[3 * VL * c + k];
    }
    for (int k = 0; k < GF_SIZE * VL; ++k) FL[k] += GF[k];
}

/* The regular-point test (see the top) for VL points side by side: bad (VL) is set to 1 for the
 * lanes that some face makes irregular; far (T, VL) is 1 where a face takes the far-field rule. */
static void classify_lanes(const double *P, const int *tri, long T, const double *nrm, const double *two_area,
                           const double *longest, const unsigned char *thin, const double *x0, const double *x1,
                           const double *x2, double far_c, double near_c, double vertex_c, double tol, double *bad,
                           double *far) {
    for (long f = 0; f < T; ++f) {
        const int *t = tri + 3 * f;
        const double *q0 = P + 3 * t[0], *q1 = P + 3 * t[1], *q2 = P + 3 * t[2], *nv = nrm + 3 * f;
        const double fd = far_c * longest[f], vc2 = vertex_c * vertex_c;
        const int lost = !(two_area[f] > 0), is_thin = thin[f] != 0, has_far = longest[f] > 0;
#pragma omp simd
        for (int l = 0; l < VL; ++l) {
            double a0x = q0[0] - x0[l], a0y = q0[1] - x1[l], a0z = q0[2] - x2[l];
            double a1x = q1[0] - x0[l], a1y = q1[1] - x1[l], a1z = q1[2] - x2[l];
            double a2x = q2[0] - x0[l], a2y = q2[1] - x1[l], a2z = q2[2] - x2[l];
            double r0 = a0x * a0x + a0y * a0y + a0z * a0z, r1 = a1x * a1x + a1y * a1y + a1z * a1z;
            double r2 = a2x * a2x + a2y * a2y + a2z * a2z;
            double rmin2 = r0 < r1 ? r0 : r1, rmax2 = r0 < r1 ? r1 : r0;
            rmin2 = r2 < rmin2 ? r2 : rmin2, rmax2 = r2 > rmax2 ? r2 : rmax2;
            int is_far = has_far & (rmin2 >= fd * fd);
            double h = fabs(DOTA(0, nv));
            int closed_bad = is_thin | !(h * h >= near_c * near_c * rmin2) | !(h > tol) | !(rmin2 >= vc2 * rmax2);
            bad[l] = (lost | ((is_far == 0) & closed_bad)) ? 1.0 : bad[l];
            far[f * VL + l] = is_far ? 1.0 : 0.0;
        }
    }
}

/* One batch element's arrays (the layouts at the top). */
typedef struct {
    const double *P, *nrm, *edir, *eout, *gbary, *gnorm, *two_area, *longest, *far_nodes, *far_w, *X, *GPHI, *GPSI;
    const unsigned char *thin;
    double tol, *GX, *GA, *GF, *GN, *GW;
    unsigned char *reg;
} vjp_element;

/* The sizes every element shares. */
typedef struct {
    const int *tri;
    const double *far_bary;
    long V, T, Q, n;
    double far_c, near_c, vertex_c;
} vjp_shape;

/* A thread's scratch: lane-by-lane sums of the corners' (V, 3, VL) and the face constants'
 * (T, GF_SIZE, VL) cotangents; the far-field rule's sums: corners (V, 3), face constants
 * (T, GF_SIZE), nodes (T, Q, 3), weights (T, Q); a block's far flags (T, VL); one face's lanes. */
typedef struct {
    double *cl, *fl, *ga, *gf, *gn, *gw, *farl, *lane_ga, *lane_gf;
    size_t sums; /* the length of the sums, from cl to gw */
} vjp_scratch;

static vjp_scratch scratch_of(double *ws, const vjp_shape *s) {
    const long V = s->V, T = s->T, Q = s->Q;
    vjp_scratch w;
    w.cl = ws, w.fl = ws + 3 * V * VL, w.ga = w.fl + GF_SIZE * T * VL, w.gf = w.ga + 3 * V;
    w.gn = w.gf + GF_SIZE * T, w.gw = w.gn + 3 * T * Q, w.farl = w.gw + T * Q;
    w.lane_ga = w.farl + T * VL, w.lane_gf = w.lane_ga + 9 * VL;
    w.sums = (size_t)(w.farl - ws);
    return w;
}

static size_t scratch_size(const vjp_shape *s) {
    return (size_t)(3 * s->V + GF_SIZE * s->T) * (VL + 1) + 4 * (size_t)(s->T * s->Q) + (size_t)s->T * VL +
           (9 + GF_SIZE) * VL;
}

/* Block ib (VL points) of element e: its points' rows of GX and reg, its sums into w. w == NULL:
 * no scratch, the points are left to the caller. Returns whether a point was regular (w used). */
static int vjp_block(const vjp_element *e, const vjp_shape *s, long ib, const vjp_scratch *w) {
    const long V = s->V, T = s->T, Q = s->Q, n = s->n, i0 = VL * ib;
    const int *tri = s->tri;
    const int cnt = n - i0 < VL ? (int)(n - i0) : VL;
    double xl[3][VL], bad[VL], okc[VL], gxl[3][VL], bp[3][VL], bps[VL];
    long row[VL];
    for (int l = 0; l < VL; ++l) {
        row[l] = i0 + (l < cnt ? l : cnt - 1); /* padded lanes repeat the last point, bad */
        for (int k = 0; k < 3; ++k) xl[k][l] = e->X[3 * row[l] + k], gxl[k][l] = 0.0;
        bad[l] = l < cnt && w != NULL ? 0.0 : 1.0;
    }
    if (w != NULL)
        classify_lanes(e->P, tri, T, e->nrm, e->two_area, e->longest, e->thin, xl[0], xl[1], xl[2], s->far_c,
                       s->near_c, s->vertex_c, e->tol, bad, w->farl);
    int any = 0;
    for (int l = 0; l < cnt; ++l) e->reg[i0 + l] = bad[l] == 0, any |= bad[l] == 0;
    for (long f = 0; any && f < T; ++f) {
        const int *t = tri + 3 * f;
        const double *q[3] = {e->P + 3 * t[0], e->P + 3 * t[1], e->P + 3 * t[2]};
        int nclosed = 0, nfar = 0;
        for (int l = 0; l < VL; ++l) {
            for (int c = 0; c < 3; ++c) bp[c][l] = e->GPHI[V * row[l] + t[c]] / FOUR_PI;
            bps[l] = e->GPSI[T * row[l] + f] / FOUR_PI;
            okc[l] = bad[l] == 0 && w->farl[f * VL + l] == 0 ? 1.0 : 0.0;
            nclosed += okc[l] != 0, nfar += bad[l] == 0 && w->farl[f * VL + l] != 0;
        }
        if (nclosed) {
            const face_in fi = {e->nrm + 3 * f, e->edir + 9 * f, e->eout + 9 * f, e->gbary + 9 * f, e->gnorm + 3 * f};
            closed_lanes(q[0], q[1], q[2], &fi, xl[0], xl[1], xl[2], bp[0], bp[1], bp[2], bps, okc,
                         w->cl + 3 * VL * t[0], w->cl + 3 * VL * t[1], w->cl + 3 * VL * t[2],
                         w->fl + GF_SIZE * VL * f, gxl[0], w->lane_ga, w->lane_gf);
        }
        for (int l = 0; nfar && l < VL; ++l) {
            if (bad[l] != 0 || okc[l] != 0) continue;
            const double x[3] = {xl[0][l], xl[1][l], xl[2][l]};
            const double a0[3] = {q[0][0] - x[0], q[0][1] - x[1], q[0][2] - x[2]};
            const double bphi[3] = {bp[0][l], bp[1][l], bp[2][l]};
            double ga0[3] = {0, 0, 0}, gx[3] = {0, 0, 0};
            far_pair(x, a0, e->nrm + 3 * f, e->far_nodes + 3 * Q * f, e->far_w + Q * f, s->far_bary, Q, bphi, bps[l],
                     ga0, gx, w->gf + GF_SIZE * f + GF_N, w->gn + 3 * Q * f, w->gw + Q * f);
            for (int k = 0; k < 3; ++k) w->ga[3 * t[0] + k] += ga0[k], gxl[k][l] += gx[k] - ga0[k];
        }
    }
    for (int l = 0; l < cnt; ++l)
        for (int k = 0; k < 3; ++k) e->GX[3 * (i0 + l) + k] = bad[l] == 0 ? gxl[k][l] : 0.0;
    return any;
}

/* A thread's sums of element e added to its outputs (under the caller's critical section). */
static void add_sums(const vjp_element *e, const vjp_shape *s, const vjp_scratch *w) {
    for (size_t k = 0; k < 3 * (size_t)s->V; ++k) {
        double sum = w->ga[k];
        for (int l = 0; l < VL; ++l) sum += w->cl[k * VL + l];
        e->GA[k] += sum;
    }
    for (size_t k = 0; k < GF_SIZE * (size_t)s->T; ++k) {
        double sum = w->gf[k];
        for (int l = 0; l < VL; ++l) sum += w->fl[k * VL + l];
        e->GF[k] += sum;
    }
    for (size_t k = 0; k < 3 * (size_t)(s->T * s->Q); ++k) e->GN[k] += w->gn[k];
    for (size_t k = 0; k < (size_t)(s->T * s->Q); ++k) e->GW[k] += w->gw[k];
}

/* B elements: element b's arrays start b (one element's size) into each of first's, its on-cage
 * tolerance is tol[b]. */
static void vjp_run(long B, const vjp_element *first, const double *tol, const vjp_shape *s, int nthreads) {
    const long V = s->V, T = s->T, Q = s->Q, n = s->n, nb = (n + VL - 1) / VL;
    memset(first->GA, 0, sizeof(double) * 3 * (size_t)(B * V));
    memset(first->GF, 0, sizeof(double) * GF_SIZE * (size_t)(B * T));
    memset(first->GN, 0, sizeof(double) * 3 * (size_t)(B * T * Q));
    memset(first->GW, 0, sizeof(double) * (size_t)(B * T * Q));
    int failed = 0;
#pragma omp parallel num_threads(nthreads)
    {
        double *ws = (double *)malloc(sizeof(double) * scratch_size(s));
        if (ws == NULL) {
#pragma omp atomic write
            failed = 1;
        }
        vjp_scratch w;
        int dirty = 1; /* whether the sums hold something (cleared, and added, only then) */
        if (ws != NULL) w = scratch_of(ws, s);
        for (long b = 0; b < B; ++b) {
            const vjp_element *f = first;
            const vjp_element e = {
                f->P + 3 * V * b,         f->nrm + 3 * T * b,          f->edir + 9 * T * b,  f->eout + 9 * T * b,
                f->gbary + 9 * T * b,     f->gnorm + 3 * T * b,        f->two_area + T * b,  f->longest + T * b,
                f->far_nodes + 3 * T * Q * b, f->far_w + T * Q * b,    f->X + 3 * n * b,     f->GPHI + n * V * b,
                f->GPSI + n * T * b,      f->thin + T * b,             tol[b],               f->GX + 3 * n * b,
                f->GA + 3 * V * b,        f->GF + GF_SIZE * T * b,     f->GN + 3 * T * Q * b, f->GW + T * Q * b,
                f->reg + n * b};
            if (ws != NULL && dirty) memset(ws, 0, sizeof(double) * w.sums);
            dirty = 0;
            /* (nowait: each thread adds its own sums below, whatever the others are doing) */
#pragma omp for schedule(dynamic, 4) nowait
            for (long ib = 0; ib < nb; ++ib) dirty |= vjp_block(&e, s, ib, ws != NULL ? &w : NULL);
            if (ws != NULL && dirty) {
#pragma omp critical
                add_sums(&e, s, &w);
            }
        }
        free(ws);
    }
    if (failed && B * n > 0) first->GX[0] = NAN; /* (the caller raises MemoryError: check_workspace) */
}

/* The products for B cages with one topology (the arguments and outputs of the comment at the top,
 * each per-cage one with a leading B; tol (B,)): element by element the same blocks, in one parallel
 * region. */
void tc_gc3d_vjp_batch(long B, const double *P, long V, const int *tri, long T, const double *nrm,
                       const double *edir, const double *eout, const double *gbary, const double *gnorm,
                       const double *two_area, const double *longest, const unsigned char *thin,
                       const double *far_nodes, const double *far_w, const double *far_bary, long Q, double far_c,
                       double near_c, double vertex_c, const double *tol, const double *X, long n,
                       const double *GPHI, const double *GPSI, int nthreads, double *GX, double *GA, double *GF,
                       double *GN, double *GW, unsigned char *reg) {
    const vjp_element e = {P, nrm, edir, eout, gbary, gnorm, two_area, longest, far_nodes, far_w, X, GPHI, GPSI,
                           thin, 0.0, GX, GA, GF, GN, GW, reg};
    const vjp_shape s = {tri, far_bary, V, T, Q, n, far_c, near_c, vertex_c};
    vjp_run(B, &e, tol, &s, nthreads);
}
