/*
 * Native CPU kernel of the quad part of torchcage's Green coordinates for triquad cages (float64).
 *
 * The same steps as torchcage/families/quad_green/kernel.py (see its docstring): per point and quad, the
 * smooth projection (tc_quad_pair_c, shared with QMVC), the invariants from exact triangle Green
 * integrals (outside the quad's tetrahedron on its split triangles, computed for all quads at once
 * per point by tc_gc_point; inside it on the fan of four triangles from the projection to the
 * edges, tc_tri_green), the least-norm solution through the precomputed pseudo-inverse of A_q, and
 * the null-space part from the adaptive Riemann sum of Algorithm 1 (edge integrals once per unique
 * pattern edge, then one vectorised loop over the sub-triangles). On the Riemann sub-triangles the
 * solid angle is taken in Van Oosterom and Strackee's one-atan2 form (the estimate needs no more);
 * the tests check this kernel against the torch kernel. The Riemann form takes QL (8) points per quad
 * side by side (tc_quad_pair_lanes, shared with QMVC, and riemann_lanes: each lane's operations as the
 * one-point code's, with the node and edge tables stored [node][lane], so the sub-triangle loop loads
 * contiguous lanes instead of gathering), the lanes tc_quad_pair_lanes cannot serve going to the
 * one-point code (pair_one); the tolerance form one point at a time. OpenMP over points (blocks).
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

/* The fan's apex moves along the projection's ruling, away from the nearest edge, to FAN_APEX_BAND
 * of the parameter range or to the distance of the nearest perpendicular edge (as fan_apex in
 * _qgc3d.py: the fan triangle over a nearby edge is no longer a sliver). */
#define FAN_APEX_BAND 0.25

static void fan_apex(double u, double v, double *ua, double *va) {
    double mu = fmin(u, 1 - u), mv = fmin(v, 1 - v);
    *ua = u;
    *va = v;
    if (mv <= mu) {
        double t = fmin(mu, FAN_APEX_BAND);
        *va = v <= 0.5 ? fmax(v, t) : fmin(v, 1 - t);
    } else {
        double t = fmin(mv, FAN_APEX_BAND);
        *ua = u <= 0.5 ? fmax(u, t) : fmin(u, 1 - t);
    }
}

/* Whether the point (corners p relative to it) lies within 1.1 times the quad's bounding radius of
 * its centre: every point near one of its edges does. */
static int near_quad(const double p[4][3]) {
    double m[3], r2 = 0;
    for (int c = 0; c < 3; ++c) m[c] = 0.25 * (p[0][c] + p[1][c] + p[2][c] + p[3][c]);
    for (int k = 0; k < 4; ++k) {
        double e[3] = {p[k][0] - m[0], p[k][1] - m[1], p[k][2] - m[2]};
        r2 = fmax(r2, dot3(e, e));
    }
    return dot3(m, m) <= 1.21 * r2;
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

/* What the pairs share: the cage, the quads' tables, the split triangles' tables and the Riemann
 * pattern (see tc_qgc3d). */
typedef struct {
    const double *P, *pinv, *null, *origin, *s_nrm, *s_ell, *s_edir;
    const int *quads, *s_tri;
    long T2, Pn, NE;
    int G;
    double tol;
    const int *node, *TE, *EJ, *EK;
    const int *UN; /* the NU grid nodes the pattern uses (Algorithm 1's triangles skip some) */
    long NU;
    const double *TS; /* +1 or -1: the edge opposite a triangle's corner, in the order of EJ -> EK or not */
    const double *UA, *UB, *VA, *VB, *GA, *GB;
} qgc_ctx;

/* Scratch of one lane of the Riemann sum: the grid nodes (x, y, z, R) and the edges' tables (QE,
 * 1 / length, w, D). */
#define RIEMANN_BUF(G, NE) (4 * (size_t)(G) * (G) + 6 * (size_t)(NE))

#define LANES _Pragma("omp simd") for (int j = 0; j < QL; ++j)

/* The invariants rhs of quad q seen from x (corners minus the point p, projection (u, v)); SP, SPSI:
 * the point's split-triangle tables (tc_gc_point). */
static void pair_rhs(const qgc_ctx *C, long q, const double *x, const double p[4][3], double u, double v, int inside,
                     int on, const double *SP, const double *SPSI, double rhs[4]) {
    const double *P = C->P, *origin = C->origin;
    const int *qi = C->quads + 4 * q;
    const long T2 = C->T2;
    rhs[0] = rhs[1] = rhs[2] = rhs[3] = 0;
    /* Outside the quad's tetrahedron the point cannot lie between the sheet and the split
     * (q0 q1 q2), (q0 q2 q3): those two triangles give the same invariants, already
     * computed for all quads above. Within 1.1 times the quad's bounding radius of its
     * centre, the fan instead, as for the quads around: near an edge, two quads must see
     * it in the same form (split and fan treat the point's side of the edge with
     * different bits, and their errors of eps / distance did not cancel). */
    if (!inside && !on && !near_quad(p)) {
        for (long t = 2 * q; t < 2 * q + 2; ++t) {
            for (int i = 0; i < 3; ++i) {
                double ph = SP[i * T2 + t];
                const double *c3 = P + 3 * C->s_tri[i * T2 + t];
                for (int c = 0; c < 3; ++c) rhs[c] += ph * (c3[c] - origin[c]);
                rhs[3] += ph;
            }
            for (int c = 0; c < 3; ++c) rhs[c] += SPSI[t] * C->s_nrm[3 * t + c];
        }
        return;
    }
    /* On the fan from the projection (apex) to the four edges. The fan's frames from the corners
     * themselves (a quad edge then has the bits of the neighbouring quad's fan or triangle face:
     * consistent sides near it). */
    double apex[3], ua = u, va = v;
    if (!on) fan_apex(u, v, &ua, &va);
    const double wq[4] = {(1 - ua) * (1 - va), ua * (1 - va), ua * va, (1 - ua) * va};
    for (int c = 0; c < 3; ++c)
        apex[c] = wq[0] * P[3 * qi[0] + c] + wq[1] * P[3 * qi[1] + c] + wq[2] * P[3 * qi[2] + c] +
                  wq[3] * P[3 * qi[3] + c];
    for (int e = 0; e < 4; ++e) {
        double ab[3][3], a[3][3], nf[3], ell[3], edir[9], eout[9], gbary[9], ph[3], ps, om, al[3];
        memcpy(ab[0], P + 3 * qi[e], sizeof(ab[0]));
        memcpy(ab[1], P + 3 * qi[(e + 1) & 3], sizeof(ab[1]));
        memcpy(ab[2], apex, sizeof(ab[2]));
        for (int i = 0; i < 3; ++i)
            for (int c = 0; c < 3; ++c) a[i][c] = ab[i][c] - x[c];
        double two_area = tc_tri_frame(ab, nf, ell, edir, eout, gbary);
        /* The quad edge (opposite the apex) with the bits Python gave it in the split
         * triangles' tables, the function that made the cage faces' (a triangle face
         * across the edge then sees the point on the same side: PU was off by 7e-6 at
         * 4e-14 from such an edge of Beast, the C and torch norms differing by an ulp). */
        {
            const long t = e < 2 ? 2 * q : 2 * q + 1;
            const int ci = e == 0 ? 2 : (e == 3 ? 1 : 0);
            for (int c = 0; c < 3; ++c) edir[6 + c] = C->s_edir[9 * t + 3 * ci + c];
            ell[2] = C->s_ell[3 * t + ci];
            cross3(edir + 6, nf, eout + 6);
            for (int c = 0; c < 3; ++c) gbary[6 + c] = two_area > 0 ? -eout[6 + c] * ell[2] / two_area : 0.0;
        }
        /* The apex on this edge (a point on the quad's boundary): the triangle is
         * empty, up to rounding that would make it a sliver seen from its own edge. */
        if (two_area <= C->tol * ell[2]) continue;
        tc_tri_green(a, nf, two_area, ell, edir, eout, gbary, C->tol, ph, &ps, &om, al);
        for (int i = 0; i < 3; ++i) {
            for (int c = 0; c < 3; ++c) rhs[c] += ph[i] * (ab[i][c] - origin[c]);
            rhs[3] += ph[i];
        }
        for (int c = 0; c < 3; ++c) rhs[c] += ps * nf[c];
    }
}

/* The least-norm solution bar = A_q^+ rhs, plus the null-space part from est (with the norm
 * correction when norm), into the point's phi and psiq. */
static void pair_finish(const qgc_ctx *C, long q, const double rhs[4], const double est[8], int norm, double *phi,
                        double *psiq) {
    const double *Ap = C->pinv + 32 * q, *Nl = C->null + 32 * q;
    const int *qi = C->quads + 4 * q;
    double bar[8];
    for (int i = 0; i < 8; ++i)
        bar[i] = Ap[4 * i] * rhs[0] + Ap[4 * i + 1] * rhs[1] + Ap[4 * i + 2] * rhs[2] + Ap[4 * i + 3] * rhs[3];
    /* Phi = Phi_bar + sum_i lambda_i kappa_i with the norm correction (none with qtol). */
    double eb = 0, bb = 0, coef[4];
    for (int i = 0; i < 8; ++i) {
        eb += est[i] * bar[i];
        bb += bar[i] * bar[i];
    }
    double scale = !norm ? 1.0 : (eb != 0 ? bb / eb : 0.0);
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

#if defined(__GNUC__)
#define QGC_INLINE inline __attribute__((always_inline))
#else
#define QGC_INLINE inline
#endif

/* One sub-triangle of the Riemann sum, written once for riemann_one and riemann_lanes (inlined in
 * their vector loops): corners a_i relative to the point with R_i = |a_i|; for the edge opposite
 * corner i (from corner j = i + 1 to k = i + 2), its tables in the orientation of the pattern's edge
 * list, s_i = +1 or -1 the triangle's orientation of it: w_i = s_i a_j x a_k, D_i = a_j . a_k and
 * QE_i = int dl / r over its length; the centroid's (uc, vc).
 * *so: the solid angle over 4 pi (Van Oosterom-Strackee: tan(omega / 2) = det / den, det = h 2A =
 * a_0 . (a_1 x a_2), den = R0 R1 R2 + D_0 R0 + D_1 R1 + D_2 R2);
 * *sp: psi = (sum_e d_e I_e - h omega) / 4 pi over the sheet normal's length at the centroid, d_e
 * the signed distance of the foot point to edge e's line, d_e |E_e| 2A = a_j . (E_e x cr) = cr .
 * (a_j x a_k) with E_e = a_k - a_j: the edge's cross product, shared by the triangles on both sides
 * (the edge tables hold I_e / |E_e| as QE). */
static QGC_INLINE void subtri_terms(double a0x, double a0y, double a0z, double R0, double a1x, double a1y, double a1z,
                                    double R1, double a2x, double a2y, double a2z, double R2, double s0, double s1,
                                    double s2, double w0x, double w0y, double w0z, double w1x, double w1y,
                                    double w1z, double w2x, double w2y, double w2z, double D0,
                                    double D1, double D2, double qe0, double qe1, double qe2, double uc, double vc,
                                    const double *N0, const double *Nu, const double *Nv, double tol, double *so,
                                    double *sp) {
    const double inv4pi = 1.0 / FOUR_PI;
    double f1x = a1x - a0x, f1y = a1y - a0y, f1z = a1z - a0z;
    double f2x = a2x - a0x, f2y = a2y - a0y, f2z = a2z - a0z;
    double crx = f1y * f2z - f1z * f2y, cry = f1z * f2x - f1x * f2z, crz = f1x * f2y - f1y * f2x;
    double two_area = sqrt(crx * crx + cry * cry + crz * crz);
    double det = s0 * (a0x * w0x + a0y * w0y + a0z * w0z);
    double den = R0 * R1 * R2 + D0 * R0 + D1 * R1 + D2 * R2;
    double omv = 2.0 * atan2(det, den);
    double om = ((det >= 0 ? det : -det) <= tol * two_area || two_area == 0) ? 0.0 : omv;
    double m0 = crx * w0x + cry * w0y + crz * w0z;
    double m1 = crx * w1x + cry * w1y + crz * w1z;
    double m2 = crx * w2x + cry * w2y + crz * w2z;
    double Ncx = N0[0] + uc * Nu[0] + vc * Nv[0], Ncy = N0[1] + uc * Nu[1] + vc * Nv[1];
    double Ncz = N0[2] + uc * Nu[2] + vc * Nv[2], Nn = sqrt(Ncx * Ncx + Ncy * Ncy + Ncz * Ncz);
    /* psi_t / |N| = (sum_e m_e QE_e - det omega) / (4 pi 2A |N|) */
    double an = two_area * Nn, r = an >= 0x1p-1022 ? inv4pi / an : 0.0; /* (1 / an finite: no 0 * inf) */
    *sp = (s0 * m0 * qe0 + s1 * m1 * qe1 + s2 * m2 * qe2 - det * om) * r;
    *so = om * inv4pi;
}

/* One edge of the pattern (nodes a_j -> a_k relative to the point, R = |a|): its tables for
 * subtri_terms (w = a_j x a_k, D = a_j . a_k), the argument of its log-integral int dl / r (the log is
 * taken in a loop of its own, vectorised with libmvec) and *invl = 1 / length (0 for a degenerate
 * edge). The argument is tc_edge_log_arg's, with l_j = a_j . u, l_k = a_k . u and c2 = |a_j x u|^2
 * for u = E / ell, E = a_k - a_j, each quotient's terms multiplied by ell (the third's by ell^2), so
 * that one division gives both it and 1 / ell. */
static QGC_INLINE void edge_terms(double ajx, double ajy, double ajz, double Rj, double akx, double aky, double akz,
                                  double Rk, double *wx, double *wy, double *wz, double *D, double *arg,
                                  double *invl) {
    double Ex = akx - ajx, Ey = aky - ajy, Ez = akz - ajz;
    double ell2 = Ex * Ex + Ey * Ey + Ez * Ez, ell = sqrt(ell2);
    double cx = ajy * akz - ajz * aky, cy = ajz * akx - ajx * akz, cz = ajx * aky - ajy * akx;
    double ljE = ajx * Ex + ajy * Ey + ajz * Ez, lkE = ljE + ell2; /* ell l_j, ell l_k */
    double pk = Rk * ell + lkE, mj = Rj * ell - ljE;
    double num = ljE >= 0 ? pk : (lkE <= 0 ? mj : pk * mj);
    double den = ljE >= 0 ? Rj * ell + ljE : (lkE <= 0 ? Rk * ell - lkE : cx * cx + cy * cy + cz * cz);
    den = den > 1e-300 ? den : 1e-300; /* (on the edge's line: then w = 0, and QE only needs to be finite) */
    /* (dl below 1e-300, reached only there or on a degenerate edge, is clamped too: 1 / dl must not
     * overflow, or QE = log(.) / ell would be inf and w . cr QE NaN) */
    double dl = den * ell, r = ell > 0 ? 1.0 / (dl > 1e-300 ? dl : 1e-300) : 0.0;
    double a = num * ell * r;
    a = num > 0 && ell > 0 ? (a < 1e300 ? a : 1e300) : 1.0;
    *wx = cx;
    *wy = cy;
    *wz = cz;
    *D = ajx * akx + ajy * aky + ajz * akz;
    *arg = a > 1e-300 ? a : 1e-300;
    *invl = den * r;
}

/* Riemann estimate on the adaptive tessellation (Algorithm 1, Eqs. 17-18) of one pair: p0 the
 * first corner minus the point, (u, v) the projection; buf: RIEMANN_BUF(G, NE) scratch. */
static void riemann_one(const qgc_ctx *C, const quad_const *qc, const double *p0, double u, double v, double *buf,
                        double est[8]) {
    const int G = C->G;
    const long Pn = C->Pn, NE = C->NE;
    const int *node = C->node, *TE = C->TE, *EJ = C->EJ, *EK = C->EK;
    const double *TS = C->TS;
    const double *UA = C->UA, *UB = C->UB, *VA = C->VA, *VB = C->VB, *GA = C->GA, *GB = C->GB;
    const double tol = C->tol;
    const double *b = qc->b, *cc = qc->cc, *dd = qc->dd;
    double *Sx = buf, *Sy = Sx + G * G, *Sz = Sy + G * G, *SR = Sz + G * G;
    double *QE = SR + G * G, *EINV = QE + NE, *Wx = EINV + NE, *Wy = Wx + NE, *Wz = Wy + NE, *DE = Wz + NE;
    const double p0x = p0[0], p0y = p0[1], p0z = p0[2];
    const int *UN = C->UN;
#pragma omp simd
    for (long i = 0; i < C->NU; ++i) { /* grid nodes on the quad, minus the point */
        const long g = UN[i];
        double uu = GA[g] + GB[g] * u, vv = GA[G * G + g] + GB[G * G + g] * v, uv = uu * vv;
        double sx = p0x + uu * b[0] + vv * cc[0] + uv * dd[0];
        double sy = p0y + uu * b[1] + vv * cc[1] + uv * dd[1];
        double sz = p0z + uu * b[2] + vv * cc[2] + uv * dd[2];
        Sx[g] = sx;
        Sy[g] = sy;
        Sz[g] = sz;
        SR[g] = sqrt(sx * sx + sy * sy + sz * sz);
    }
    const double *N0 = qc->N0, *Nu = qc->Nu, *Nv = qc->Nv;
#pragma omp simd
    for (long e = 0; e < NE; ++e) {
        int j = EJ[e], k = EK[e];
        edge_terms(Sx[j], Sy[j], Sz[j], SR[j], Sx[k], Sy[k], Sz[k], SR[k], Wx + e, Wy + e, Wz + e, DE + e, QE + e,
                   EINV + e);
    }
#pragma omp simd
    for (long e = 0; e < NE; ++e) QE[e] = log(QE[e]) * EINV[e];
    /* Sub-triangles (subtri_terms) and the bilinear basis at their centroids. */
    double e0 = 0, e1 = 0, e2 = 0, e3 = 0, e4 = 0, e5 = 0, e6 = 0, e7 = 0;
#pragma omp simd reduction(+ : e0, e1, e2, e3, e4, e5, e6, e7)
    for (long t = 0; t < Pn; ++t) {
        const int i0 = node[t], i1 = node[Pn + t], i2 = node[2 * Pn + t];
        const int k0 = TE[t], k1 = TE[Pn + t], k2 = TE[2 * Pn + t];
        double uc = UA[t] + UB[t] * u, vc = VA[t] + VB[t] * v, so, sp;
        subtri_terms(Sx[i0], Sy[i0], Sz[i0], SR[i0], Sx[i1], Sy[i1], Sz[i1], SR[i1], Sx[i2], Sy[i2], Sz[i2], SR[i2],
                     TS[t], TS[Pn + t], TS[2 * Pn + t], Wx[k0], Wy[k0], Wz[k0], Wx[k1], Wy[k1], Wz[k1], Wx[k2], Wy[k2],
                     Wz[k2], DE[k0], DE[k1], DE[k2],
                     QE[k0], QE[k1], QE[k2], uc, vc, N0, Nu, Nv, tol, &so, &sp);
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
    est[0] = e0;
    est[1] = e1;
    est[2] = e2;
    est[3] = e3;
    est[4] = e4;
    est[5] = e5;
    est[6] = e6;
    est[7] = e7;
}

/* riemann_one for the QL lanes of tc_quad_pair_lanes (their p0, u, v) side by side, each lane's
 * operations as riemann_one's (the sums over the sub-triangles in order, not in the vector
 * reduction's order): nodes stored [node][lane], edges [edge][lane], so the sub-triangle loop loads
 * its corners' lanes contiguously (riemann_one gathers ~30 values per triangle). lbuf: QL
 * RIEMANN_BUF(G, NE) scratch; est: (8, QL). */
static void riemann_lanes(const qgc_ctx *C, const quad_const *qc, const quad_lanes *L, double *lbuf,
                          double est[8][QL]) {
    const int G = C->G;
    const long Pn = C->Pn, NE = C->NE, GG = (long)G * G;
    const int *node = C->node, *TE = C->TE, *EJ = C->EJ, *EK = C->EK;
    const double *TS = C->TS;
    const double *UA = C->UA, *UB = C->UB, *VA = C->VA, *VB = C->VB, *GA = C->GA, *GB = C->GB;
    const double tol = C->tol;
    const double *b = qc->b, *cc = qc->cc, *dd = qc->dd, *N0 = qc->N0, *Nu = qc->Nu, *Nv = qc->Nv;
    double(*Sx)[QL] = (double(*)[QL])lbuf, (*Sy)[QL] = Sx + GG, (*Sz)[QL] = Sy + GG, (*SR)[QL] = Sz + GG;
    double(*QE)[QL] = SR + GG, (*EINV)[QL] = QE + NE, (*Wx)[QL] = EINV + NE, (*Wy)[QL] = Wx + NE;
    double(*Wz)[QL] = Wy + NE, (*DE)[QL] = Wz + NE;
    const double *u = L->u, *v = L->v, *p0x = L->p[0][0], *p0y = L->p[0][1], *p0z = L->p[0][2];
    for (long i = 0; i < C->NU; ++i) { /* grid nodes on the quad, minus the points */
        const long g = C->UN[i];
        const double gau = GA[g], gbu = GB[g], gav = GA[GG + g], gbv = GB[GG + g];
        LANES {
            double uu = gau + gbu * u[j], vv = gav + gbv * v[j], uv = uu * vv;
            double sx = p0x[j] + uu * b[0] + vv * cc[0] + uv * dd[0];
            double sy = p0y[j] + uu * b[1] + vv * cc[1] + uv * dd[1];
            double sz = p0z[j] + uu * b[2] + vv * cc[2] + uv * dd[2];
            Sx[g][j] = sx;
            Sy[g][j] = sy;
            Sz[g][j] = sz;
            SR[g][j] = sqrt(sx * sx + sy * sy + sz * sz);
        }
    }
    for (long e = 0; e < NE; ++e) {
        const int jn = EJ[e], kn = EK[e];
        LANES edge_terms(Sx[jn][j], Sy[jn][j], Sz[jn][j], SR[jn][j], Sx[kn][j], Sy[kn][j], Sz[kn][j], SR[kn][j],
                         &Wx[e][j], &Wy[e][j], &Wz[e][j], &DE[e][j], &QE[e][j], &EINV[e][j]);
    }
    {
        double *qe = QE[0], *il = EINV[0];
#pragma omp simd
        for (long i = 0; i < NE * QL; ++i) qe[i] = log(qe[i]) * il[i];
    }
    double E[8][QL];
    for (int i = 0; i < 8; ++i) LANES E[i][j] = 0.0;
    for (long t = 0; t < Pn; ++t) {
        const int i0 = node[t], i1 = node[Pn + t], i2 = node[2 * Pn + t];
        const int k0 = TE[t], k1 = TE[Pn + t], k2 = TE[2 * Pn + t];
        const double uat = UA[t], ubt = UB[t], vat = VA[t], vbt = VB[t];
        const double s0 = TS[t], s1 = TS[Pn + t], s2 = TS[2 * Pn + t];
        LANES {
            double uc = uat + ubt * u[j], vc = vat + vbt * v[j], so, sp;
            subtri_terms(Sx[i0][j], Sy[i0][j], Sz[i0][j], SR[i0][j], Sx[i1][j], Sy[i1][j], Sz[i1][j], SR[i1][j],
                         Sx[i2][j], Sy[i2][j], Sz[i2][j], SR[i2][j], s0, s1, s2, Wx[k0][j], Wy[k0][j], Wz[k0][j],
                         Wx[k1][j], Wy[k1][j], Wz[k1][j], Wx[k2][j], Wy[k2][j], Wz[k2][j], DE[k0][j], DE[k1][j],
                         DE[k2][j], QE[k0][j], QE[k1][j], QE[k2][j], uc, vc, N0, Nu, Nv, tol, &so, &sp);
            double b0 = (1 - uc) * (1 - vc), b1 = uc * (1 - vc), b2 = uc * vc, b3 = (1 - uc) * vc;
            E[0][j] += b0 * so;
            E[1][j] += b1 * so;
            E[2][j] += b2 * so;
            E[3][j] += b3 * so;
            E[4][j] += b0 * sp;
            E[5][j] += b1 * sp;
            E[6][j] += b2 * sp;
            E[7][j] += b3 * sp;
        }
    }
    for (int i = 0; i < 8; ++i) LANES est[i][j] = E[i][j];
}

/* One point-quad pair by the one-point code (tc_quad_pair_c, then the invariants, the estimate and
 * their combination), into the point's phi, psiq, onq, uv. buf: riemann_one's scratch. */
static void pair_one(const qgc_ctx *C, long q, const quad_const *qc, const double *x, double qtol, const double *gl,
                     const double *SP, const double *SPSI, double *buf, double *phi, double *psiq, int *onq,
                     double *uv) {
    const int *qi = C->quads + 4 * q;
    quad_pair qp;
    tc_quad_pair_c(C->P, qi, qc, x, C->tol, 1, &qp);
    double u = qp.u, v = qp.v;
    if (qp.on && *onq < 0) { /* (a corner: its Lagrange values) */
        *onq = (int)q;
        uv[0] = qp.vertex < 0 ? u : (qp.vertex == 1 || qp.vertex == 2 ? 1.0 : 0.0);
        uv[1] = qp.vertex < 0 ? v : (qp.vertex >= 2 ? 1.0 : 0.0);
    }
    double rhs[4], est[8];
    pair_rhs(C, q, x, (const double(*)[3])qp.p, u, v, qp.inside, qp.on, SP, SPSI, rhs);
    if (qtol > 0) {
        /* the defining integrals to the tolerance (on the quad too: both integrands are
         * O(1 / r) there, the principal value is the integral); no norm correction */
        tc_quad_integrals(qp.p[0], qp.b, qp.cc, qp.dd, u, v, qp.on, qtol, gl, 1, est);
        for (int i = 0; i < 8; ++i) est[i] *= 1.0 / FOUR_PI;
    } else {
        riemann_one(C, qc, qp.p[0], u, v, buf, est);
    }
    pair_finish(C, q, rhs, est, !(qtol > 0), phi, psiq);
}

/*
 * P: (V, 3) vertices; quads: (Q, 4) int32; size: (Q,); pinv, null: (Q, 8, 4) pseudo-inverse and
 * null-space basis (columns) of A_q built on corners relative to origin (3,); pattern: (Pn, 3, 2)
 * int32 sub-triangles as (u index, v index) on a (2K+1)^2 grid; X: (n, 3). Outputs: PHI (n, V)
 * incremented by the quads' phi (principal values on the cage), PSIQ (n, 4Q), ONQ (n,) the first
 * quad a point lies on (or -1) and UV (n, 2) its projection there. s_*: the Green-kernel tables
 * (as tc_gc3d's arguments) of the quads' split triangles, 2q: (q0 q1 q2) and 2q + 1: (q0 q2 q3).
 */
static int qgc3d_one(const double *P, long V, const int *quads, long Q, const double *size, const double *pinv,
                     const double *null, const double *origin, const int *pattern, long Pn, int K, const double *X,
                     long n, double tol, double qtol, const double *gl, int nthreads, double *PHI, double *PSIQ,
                     int *ONQ, double *UV, const double *s_Pv, const int *s_tri, const int *s_edges, long s_E,
                     const double *s_eu, const int *s_fe, const double *s_nrm, const double *s_two_area,
                     const double *s_ell, const double *s_edir, const double *s_eout, const double *s_gbary) {
    const int G = 2 * K + 1;
    (void)size; /* (in the ABI; the per-quad table holds what the pairs need) */
    /* The split triangles (q0 q1 q2), (q0 q2 q3) of every quad (2q, 2q + 1), as a set for the
     * Green kernel: per point, their integrals in one vectorised pass (tc_gc_point). */
    const long T2 = 2 * Q;
    gc_tables sg = {s_Pv, V, s_tri, T2, s_edges, s_E, s_eu, s_fe, s_nrm, s_two_area, s_ell, s_edir, s_eout, s_gbary,
                    NULL};
    const int prepared = tc_gc_prepare(&sg);
    const size_t sws = tc_gc_workspace(&sg);
    /* The pattern's sub-triangles as flat grid-node indices (corner c of triangle t at [c * Pn + t])
     * and their u and v indices; its unique edges (nodes EJ, EK) and, for each triangle, the edge
     * opposite each corner (TE, same layout) with the sign of its orientation there (TS): an edge's
     * integral int dl / r and cross product are shared by the triangles on both sides. */
    int *node = (int *)malloc(sizeof(int) * (12 * (size_t)Pn + (size_t)G * G)), *iu = node + 3 * Pn;
    int *iv = iu + 3 * Pn, *TE = iv + 3 * Pn, *UN = TE + 3 * Pn, *EJ = (int *)malloc(sizeof(int) * 6 * (size_t)Pn), *EK = EJ + 3 * Pn;
    int *seen = (int *)malloc(sizeof(int) * 25 * (size_t)G * G); /* (node, offset to the other node) */
    double *UA = (double *)malloc(sizeof(double) * (7 * (size_t)Pn + 4 * (size_t)G * G));
    double *ga = (double *)malloc(sizeof(double) * 2 * (size_t)G);
    if (!prepared || !node || !EJ || !seen || !UA || !ga) { /* (the caller fills PHI with NaN) */
        free(node), free(EJ), free(seen), free(UA), free(ga);
        tc_gc_free(&sg);
        return 1;
    }
    double *UB = UA + Pn, *VA = UB + Pn, *VB = VA + Pn, *TS = VB + Pn, *GA = TS + 3 * Pn, *GB = GA + 2 * G * G;
    for (long i = 0; i < 25 * (long)G * G; ++i) seen[i] = -1;
    long NE = 0;
    for (long t = 0; t < Pn; ++t)
        for (int c = 0; c < 3; ++c) {
            long r = 3 * t + c;
            iu[c * Pn + t] = pattern[2 * r];
            iv[c * Pn + t] = pattern[2 * r + 1];
            node[c * Pn + t] = pattern[2 * r] * G + pattern[2 * r + 1];
        }
    for (long t = 0; t < Pn; ++t)
        for (int c = 0; c < 3; ++c) {
            int j = node[((c + 1) % 3) * Pn + t], k = node[((c + 2) % 3) * Pn + t];
            int lo = j < k ? j : k, hi = j < k ? k : j;
            int du = hi / G - lo / G, dv = hi % G - lo % G; /* Algorithm 1's edges span <= 2 cells */
            int *slot = du <= 2 && dv >= -2 && dv <= 2 ? seen + 25 * (long)lo + (du + 2) * 5 + (dv + 2) : NULL;
            long id = slot ? *slot : -1;
            if (!slot) /* (any other pattern: a linear search) */
                for (long e = 0; e < NE && id < 0; ++e)
                    if (EJ[e] == lo && EK[e] == hi) id = e;
            if (id < 0) {
                id = NE++;
                EJ[id] = lo;
                EK[id] = hi;
                if (slot) *slot = (int)id;
            }
            TE[c * Pn + t] = (int)id;
            TS[c * Pn + t] = j == lo ? 1.0 : -1.0;
        }
    free(seen);
    long NU = 0; /* the nodes in use */
    for (int g = 0; g < G * G; ++g) {
        int used = 0;
        for (long i = 0; i < 3 * Pn && !used; ++i) used = node[i] == g;
        if (used) UN[NU++] = g;
    }
    /* Eq. 19's nodes are affine in the centre t (node i = ga[i] + gb[i] t): so are the grid node
     * g = (i, j) = i G + j, (u_i, v_j) = (GA[g] + GB[g] u, GA[G^2 + g] + GB[G^2 + g] v), and a
     * sub-triangle's centroid (uc, vc) = (UA + UB u, VA + VB v): no per-point grid, no gathers. */
    {
        double *gb = ga + G;
        grid19(0.0, K, ga);
        grid19(1.0, K, gb);
        for (int i = 0; i < G; ++i) gb[i] -= ga[i];
        for (long t = 0; t < Pn; ++t) { /* (sums in locals: gcc 12 -O3 miscompiled the same sums
                                           * accumulated in place after a zeroing store) */
            double ua = 0.0, ub = 0.0, va = 0.0, vb = 0.0;
            for (int c = 0; c < 3; ++c) {
                ua += ga[iu[c * Pn + t]];
                ub += gb[iu[c * Pn + t]];
                va += ga[iv[c * Pn + t]];
                vb += gb[iv[c * Pn + t]];
            }
            UA[t] = ua / 3;
            UB[t] = ub / 3;
            VA[t] = va / 3;
            VB[t] = vb / 3;
        }
        for (int g = 0; g < G * G; ++g) {
            GA[g] = ga[g / G];
            GB[g] = gb[g / G];
            GA[G * G + g] = ga[g % G];
            GB[G * G + g] = gb[g % G];
        }
        free(ga);
    }
    const qgc_ctx C = {P, pinv, null, origin, s_nrm, s_ell, s_edir, quads, s_tri, T2, Pn, NE, G, tol,
                       node, TE, EJ, EK, UN, NU, TS, UA, UB, VA, VB, GA, GB};
    /* The quads' point-independent constants, once (without the table, per pair). */
    quad_const *QC = (quad_const *)malloc(sizeof(quad_const) * (size_t)(Q > 0 ? Q : 1));
    if (QC)
        for (long q = 0; q < Q; ++q) tc_quad_const(P, quads + 4 * q, QC + q);
    /* The Riemann form takes QL points per quad side by side (tc_quad_pair_lanes, riemann_lanes); the
     * tolerance form (and a failed QC) one point at a time. */
    const int lanes = !(qtol > 0) && QC;
    const int NL = lanes ? QL : 1; /* the points per block: split-triangle tables for each */
    const size_t rbuf = RIEMANN_BUF(G, NE);
    int failed = 0; /* a thread could not allocate its scratch */
#pragma omp parallel num_threads(nthreads)
    {
        double *buf = (double *)malloc(sizeof(double) * rbuf * (lanes ? QL + 1 : 1));
        double *sbuf = (double *)malloc(sizeof(double) * (sws + 5 * (size_t)T2 * NL));
        if (!buf || !sbuf) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp barrier
        if (failed) goto done; /* (every thread: none enters the worksharing loop) */
        /* lane j's tables: SPSI + j T2 (T2,), SP + 3 j T2 (3, T2), SOM + j T2 (T2,) */
        double *SPSI = sbuf + sws, *SP = SPSI + (size_t)T2 * NL, *SOM = SP + 3 * (size_t)T2 * NL;
        if (!lanes) {
#pragma omp for schedule(dynamic, 16)
            for (long pt = 0; pt < n; ++pt) {
                const double *x = X + 3 * pt;
                double *phi = PHI + pt * V, *psiq = PSIQ + pt * 4 * Q;
                ONQ[pt] = -1;
                double s_alpha[3];
                tc_gc_point(&sg, x, tol, sbuf, SPSI, SP, SOM, s_alpha);
                for (long q = 0; q < Q; ++q) {
                    quad_const qloc;
                    const quad_const *qc = QC ? QC + q : (tc_quad_const(P, quads + 4 * q, &qloc), &qloc);
                    pair_one(&C, q, qc, x, qtol, gl, SP, SPSI, buf, phi, psiq, ONQ + pt, UV + 2 * pt);
                }
            }
        } else {
            double *lbuf = buf + rbuf;
            const long nblk = (n + QL - 1) / QL;
#pragma omp for schedule(dynamic, 2)
            for (long blk = 0; blk < nblk; ++blk) {
                const long p0 = blk * QL;
                const int nl = n - p0 < QL ? (int)(n - p0) : QL; /* (the lanes past nl repeat the first) */
                for (int j = 0; j < nl; ++j) {
                    double s_alpha[3];
                    ONQ[p0 + j] = -1;
                    tc_gc_point(&sg, X + 3 * (p0 + j), tol, sbuf, SPSI + j * T2, SP + 3 * j * T2, SOM + j * T2,
                                s_alpha);
                }
                quad_lanes L;
                for (long q = 0; q < Q; ++q) {
                    const quad_const *qc = QC + q;
                    tc_quad_pair_lanes(P, quads + 4 * q, qc, X + 3 * p0, nl, tol, &L);
                    int nredo = 0;
                    for (int j = 0; j < nl; ++j) nredo += L.redo[j] != 0;
                    double est[8][QL];
                    if (nredo < nl) riemann_lanes(&C, qc, &L, lbuf, est);
                    for (int j = 0; j < nl; ++j) {
                        const long pt = p0 + j;
                        const double *x = X + 3 * pt, *SPj = SP + 3 * j * T2, *SPSIj = SPSI + j * T2;
                        double *phi = PHI + pt * V, *psiq = PSIQ + pt * 4 * Q;
                        if (L.redo[j]) { /* (a corner, a flat quad's plane, the split form: the one-point code) */
                            pair_one(&C, q, qc, x, qtol, gl, SPj, SPSIj, buf, phi, psiq, ONQ + pt, UV + 2 * pt);
                            continue;
                        }
                        const double u = L.u[j], v = L.v[j];
                        if (L.on[j] && ONQ[pt] < 0) { /* (no corner in these lanes) */
                            ONQ[pt] = (int)q;
                            UV[2 * pt] = u;
                            UV[2 * pt + 1] = v;
                        }
                        double p[4][3], rhs[4], e8[8];
                        for (int i = 0; i < 4; ++i)
                            for (int c = 0; c < 3; ++c) p[i][c] = L.p[i][c][j];
                        pair_rhs(&C, q, x, (const double(*)[3])p, u, v, L.inside[j], L.on[j], SPj, SPSIj, rhs);
                        for (int i = 0; i < 8; ++i) e8[i] = est[i][j];
                        pair_finish(&C, q, rhs, e8, 1, phi, psiq);
                    }
                }
            }
        }
    done:
        free(buf);
        free(sbuf);
    }
    tc_gc_free(&sg);
    free(QC);
    free(node);
    free(EJ);
    free(UA);
    return failed;
}

/* tc_qgc3d for B cages with one topology (quads, pattern, s_tri, s_edges, s_fe shared): each per-cage
 * table has a leading batch axis (P (B, V, 3), size (B, Q), pinv and null (B, Q, 8, 4), origin (B, 3),
 * tol (B,), s_Pv (B, 3, V), s_eu (B, 3, s_E), s_nrm (B, 2Q, 3) ...), points X (XB, n, 3) with XB = 1
 * (shared by every cage) or B, outputs PHI (B, n, V), PSIQ (B, n, 4Q), ONQ (B, n),
 * UV (B, n, 2). The cages one after the other, each parallel over its points; element by element the
 * numbers of one cage. A failed allocation: every PHI NaN (the glue raises MemoryError). */
void tc_qgc3d(long B, const double *P, long V, const int *quads, long Q, const double *size, const double *pinv,
              const double *null, const double *origin, const int *pattern, long Pn, int K, const double *X, long XB,
              long n, const double *tol, double qtol, const double *gl, int nthreads, double *PHI, double *PSIQ,
              int *ONQ, double *UV, const double *s_Pv, const int *s_tri, const int *s_edges, long s_E,
              const double *s_eu, const int *s_fe, const double *s_nrm, const double *s_two_area, const double *s_ell,
              const double *s_edir, const double *s_eout, const double *s_gbary) {
    const long T2 = 2 * Q;
    int failed = XB != 1 && XB != B; /* (the glue never passes this; never read past X: NaN, MemoryError) */
    for (long b = 0; b < B && !failed; ++b)
        failed = qgc3d_one(P + b * V * 3, V, quads, Q, size + b * Q, pinv + b * Q * 32, null + b * Q * 32, origin + 3 * b,
                           pattern, Pn, K, X + (XB > 1 ? b : 0) * n * 3, n, tol[b], qtol, gl, nthreads,
                           PHI + b * n * V, PSIQ + b * n * 4 * Q, ONQ + b * n, UV + b * n * 2, s_Pv + b * 3 * V, s_tri,
                           s_edges, s_E, s_eu + b * 3 * s_E, s_fe, s_nrm + b * T2 * 3, s_two_area + b * T2,
                           s_ell + b * T2 * 3, s_edir + b * T2 * 9, s_eout + b * T2 * 9, s_gbary + b * T2 * 9);
    if (failed) /* the glue's sign of a failed allocation (it raises MemoryError) */
        for (long k = 0; k < B * n * V; ++k) PHI[k] = NAN;
}
