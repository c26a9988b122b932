/*
 * Native CPU kernel of torchcage's 3D Green coordinates (float64): the same closed forms as
 * torchcage/families/green/kernel3d.py (see its module docstring). tc_gc_point computes one point
 * (vectorised across faces; the QGC and derivative kernels use it); tc_gc3d computes blocks of
 * GC_LANES points (gc_block: vectorised across the points, with tc_gc_point's careful forms for the
 * pairs that need them), OpenMP over blocks. The tests check it against the torch kernel.
 */
#define _GNU_SOURCE
#include <math.h>
#include <stdlib.h>
#include <string.h>
#if defined(__x86_64__) && defined(__SSE2__)
#include <emmintrin.h>
#define GC_STREAM 1
#endif

#define FOUR_PI 12.566370614359172953850573533118
#define GC_PERPENDICULAR_PLANE_RATIO 0.01 /* pairs closer to a face plane than this x min R: edge-sum solid angle */
#define GC_PERPENDICULAR_VERTEX_RATIO 1e-3 /* pairs nearer a corner than this x the farthest corner: edge-sum solid angle */

#include "native.h"

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector log and atan2 (libmvec) in the plain loops below. */
__attribute__((simd("notinbranch"))) double log(double);
__attribute__((simd("notinbranch"))) double atan2(double, double);
#endif

/* ---- Thin faces (torchcage/_core/thin_triangle.py, whose docstring derives the form) ---- */

static const double GL8_X[8] = {0.019855071751231912, 0.10166676129318664, 0.23723379504183562, 0.40828267875217505,
                                0.5917173212478251,   0.7627662049581644,  0.8983332387068135,  0.980144928248768};
static const double GL8_W[8] = {0.05061426814518814, 0.11119051722668717, 0.15685332293894366, 0.18134189168918097,
                                0.1813418916891811,  0.15685332293894366, 0.11119051722668717, 0.05061426814518822};
static const double GL12_X[12] = {0.009219682876640267, 0.047941371814762546, 0.1150486629028476, 0.20634102285669115,
                                  0.31608425050091005,  0.43738329574426554,  0.5626167042557344, 0.6839157494990902,
                                  0.7936589771433087,   0.8849513370971525,   0.9520586281852375, 0.9907803171233596};
static const double GL12_W[12] = {0.02358766819325577, 0.053469662997659366, 0.08003916427167304, 0.1015837133615329,
                                  0.11674626826917739, 0.12457352290670182,  0.12457352290670141, 0.11674626826917686,
                                  0.10158371336153309, 0.08003916427167301,  0.05346966299765926, 0.023587668193255747};

static inline double log_ratio(double num, double den) { return num > 0 && den > 0 ? log(num / den) : 0.0; }

/* M_k = int_0^1 s^k / r^3 ds (k < 3) and N_k = int_0^1 s^k / r ds (k < 2) along p0 + s (p1 - p0), the
 * point at the origin and off the segment (torch: segment_moments). */
static void segment_moments(const double *p0, const double *p1, double *M, double *N) {
    double d[3] = {p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]};
    double ell2 = dot3(d, d), ell = sqrt(ell2);
    double t = ell2 > 0 ? -dot3(p0, d) / ell2 : 0.0;
    t = t < 0 ? 0.0 : (t > 1 ? 1.0 : t);
    double q[3] = {p0[0] + t * d[0], p0[1] + t * d[1], p0[2] + t * d[2]};
    double dist = sqrt(dot3(q, q));
    if (ell < dist) { /* short next to its distance: Gauss */
        M[0] = M[1] = M[2] = N[0] = N[1] = 0.0;
        for (int k = 0; k < 12; ++k) {
            double s = GL12_X[k], w = GL12_W[k];
            double r[3] = {p0[0] + s * d[0], p0[1] + s * d[1], p0[2] + s * d[2]};
            double rr = sqrt(dot3(r, r)), i1 = w / rr, i3 = i1 / (rr * rr);
            M[0] += i3, M[1] += i3 * s, M[2] += i3 * s * s, N[0] += i1, N[1] += i1 * s;
        }
        return;
    }
    double e[3] = {d[0] / ell, d[1] / ell, d[2] / ell};
    double ua = dot3(p0, e), ub = dot3(p1, e), Ra = sqrt(dot3(p0, p0)), Rb = sqrt(dot3(p1, p1)), cr[3];
    cross3(Ra <= Rb ? p0 : p1, e, cr);
    double c2 = dot3(cr, cr), sum = ell * (ub + ua);
    double F0 = (ua > 0 || ub < 0) ? sum / (Ra * Rb * (ub * Ra + ua * Rb)) : (ub / Rb - ua / Ra) / c2;
    double F1 = sum / (Ra * Rb * (Ra + Rb));
    double A0 = ua >= 0 ? log_ratio(ub + Rb, ua + Ra)
                        : (ub <= 0 ? log_ratio(Ra - ua, Rb - ub) : log_ratio((ub + Rb) * (Ra - ua), c2));
    double F2 = A0 - c2 * F0, G1 = sum / (Ra + Rb);
    M[0] = F0 / ell;
    M[1] = (F1 - ua * F0) / ell2;
    M[2] = (F2 - 2 * ua * F1 + ua * ua * F0) / (ell2 * ell);
    N[0] = A0 / ell;
    N[1] = (G1 - ua * A0) / ell2;
}

/* 1 when the face with corners a (minus the point) is THIN_ASPECT times longer than wide and the
 * point THIN_DISTANCE widths or more from its longest edge (torch: thin_pairs). */
int tc_thin_face(const double a[3][3], double two_area) {
    if (!(two_area > 0)) return 0;
    double E[3][3], L2 = -1.0;
    int lo = 0;
    for (int i = 0; i < 3; ++i) {
        for (int c = 0; c < 3; ++c) E[i][c] = a[(i + 2) % 3][c] - a[(i + 1) % 3][c];
        double l2 = dot3(E[i], E[i]);
        if (l2 > L2) L2 = l2, lo = i;
    }
    if (!(L2 > TC_THIN_ASPECT * two_area)) return 0;
    const double *A = a[(lo + 1) % 3], *d = E[lo];
    double t = -dot3(A, d) / L2;
    t = t < 0 ? 0.0 : (t > 1 ? 1.0 : t);
    double q[3] = {A[0] + t * d[0], A[1] + t * d[1], A[2] + t * d[2]};
    return dot3(q, q) * L2 >= (TC_THIN_DISTANCE * two_area) * (TC_THIN_DISTANCE * two_area);
}

/* The swept form of a thin face's Green integrals (torch: thin_triangle_integrals): phi (3,) (corner
 * order, with 1 / 4 pi), psi, omega. Returns 1. */
int tc_thin_green(const double a[3][3], double h, double two_area, double *phi, double *psi, double *omega) {
    double L2 = -1.0;
    int lo = 0;
    for (int i = 0; i < 3; ++i) {
        double E[3] = {a[(i + 2) % 3][0] - a[(i + 1) % 3][0], a[(i + 2) % 3][1] - a[(i + 1) % 3][1],
                       a[(i + 2) % 3][2] - a[(i + 1) % 3][2]};
        double l2 = dot3(E, E);
        if (l2 > L2) L2 = l2, lo = i;
    }
    const int ord[3] = {(lo + 1) % 3, (lo + 2) % 3, lo}; /* A, B, C */
    const double *aA = a[ord[0]], *aB = a[ord[1]], *aC = a[ord[2]];
    double AB[3] = {aB[0] - aA[0], aB[1] - aA[1], aB[2] - aA[2]};
    double CA[3] = {aC[0] - aA[0], aC[1] - aA[1], aC[2] - aA[2]};
    double lam = L2 > 0 ? dot3(CA, AB) / L2 : 0.0;
    lam = lam < 0 ? 0.0 : (lam > 1 ? 1.0 : lam);
    double aF[3] = {aA[0] + lam * AB[0], aA[1] + lam * AB[1], aA[2] + lam * AB[2]};
    double j1 = two_area * lam, j2 = two_area * (1 - lam), hat[3] = {0.0, 0.0, 0.0}, inv3 = 0.0, inv1 = 0.0;
    for (int m = 0; m < 8; ++m) {
        double tau = GL8_X[m], wt = GL8_W[m], M[3], N[2];
        double aCt[3] = {aF[0] + tau * (aC[0] - aF[0]), aF[1] + tau * (aC[1] - aF[1]), aF[2] + tau * (aC[2] - aF[2])};
        double bC[3] = {(1 - tau) * (1 - lam), (1 - tau) * lam, tau};
        /* A -> C_tau: hats bA + s (bC - bA), area element j1 s */
        segment_moments(aA, aCt, M, N);
        for (int i = 0; i < 3; ++i) {
            double g0 = i == 0 ? 1.0 : 0.0, g1 = bC[i] - g0;
            hat[i] += wt * j1 * (g0 * M[1] + g1 * M[2]);
        }
        inv3 += wt * j1 * M[1];
        inv1 += wt * j1 * N[1];
        /* C_tau -> B: hats bC + s (bB - bC), area element j2 (1 - s) */
        segment_moments(aCt, aB, M, N);
        for (int i = 0; i < 3; ++i) {
            double g0 = bC[i], g1 = (i == 1 ? 1.0 : 0.0) - g0;
            hat[i] += wt * j2 * (g0 * M[0] + g1 * M[1] - g0 * M[1] - g1 * M[2]);
        }
        inv3 += wt * j2 * (M[0] - M[1]);
        inv1 += wt * j2 * (N[0] - N[1]);
    }
    for (int i = 0; i < 3; ++i) phi[ord[i]] = h * hat[i] / FOUR_PI;
    *psi = inv1 / FOUR_PI;
    *omega = h * inv3;
    return 1;
}

/* The solid angle's edge sum (no cancellation near the face's plane) over a face's three edges, edge
 * e's term atan2(d l_k, R0sq + habs R_k) - atan2(d l_j, R0sq + habs R_j): d the foot point's signed
 * distance to the edge line, l_j, l_k, R_j, R_k as in tc_edge_log_arg, R0sq = d^2 + h^2, habs =
 * |h|. The six atan2 run in one vector loop of fixed length (in the AVX2 build, libmvec's four-lane
 * form twice: a scalar atan2 took ten times as long per value), so that within a build the bits
 * depend on the arguments alone. */
static inline double edge_angle_sum(const double *d, const double *l_j, const double *l_k, const double *R_j,
                                    const double *R_k, const double *R0sq, double habs) {
    double y[8], x[8], t[8];
    for (int e = 0; e < 3; ++e) {
        y[2 * e] = d[e] * l_k[e], x[2 * e] = R0sq[e] + habs * R_k[e];
        y[2 * e + 1] = d[e] * l_j[e], x[2 * e + 1] = R0sq[e] + habs * R_j[e];
    }
    y[6] = y[7] = 0.0, x[6] = x[7] = 1.0;
#pragma omp simd
    for (int i = 0; i < 8; ++i) t[i] = atan2(y[i], x[i]);
    return ((t[0] - t[1]) + (t[2] - t[3])) + (t[4] - t[5]);
}

/* The Green integrals of a face from its distance h to the point, solid angle om, the signed
 * distances d (3,) of the foot point to the edge lines and the edge integrals I (3,): phi (3,) (may
 * be NULL), psi and the foot point's barycentric coordinates alpha (3,). */
static inline void face_finish(double h, double om, int on_plane, const double *d, const double *I, const double *ell,
                               const double *eout, const double *gbary, double two_area, double *phi, double *psi,
                               double *alpha) {
    double K[3] = {0.0, 0.0, 0.0}, dI = 0.0;
    for (int e = 0; e < 3; ++e) {
        if (!on_plane)
            for (int c = 0; c < 3; ++c) K[c] -= eout[3 * e + c] * I[e];
        if (d[e] != 0) dI += d[e] * I[e];
    }
    for (int i = 0; i < 3; ++i) {
        alpha[i] = two_area > 0 ? d[i] * ell[i] / two_area : 0.0;
        if (phi) phi[i] = (alpha[i] * om + h * dot3(gbary + 3 * i, K)) / FOUR_PI;
    }
    *psi = (dI - h * om) / FOUR_PI;
}

/* Green integrals of one triangle seen from a point (see triangle_integrals in _green3d.py):
 * a: corners minus the point; nf: unit normal; two_area; ell: (3,) length of the edge opposite each
 * corner; edir, eout, gbary: (3, 3) that edge's unit direction (p_{i+1} -> p_{i+2}), outward in-plane
 * normal and the corner's hat-function gradient. Outputs phi (3,) (may be NULL), psi, omega; alpha
 * (3,), the barycentric coordinates of the foot point; returns 1 when the point is on the face. */
int tc_tri_green(const double a[3][3], const double *nf, double two_area, const double *ell, const double *edir,
                 const double *eout, const double *gbary, double tol, double *phi, double *psi, double *omega,
                 double *alpha) {
    if (!(two_area > 0)) { /* a degenerate triangle integrates to nothing */
        for (int i = 0; i < 3; ++i) {
            alpha[i] = 0.0;
            if (phi) phi[i] = 0.0;
        }
        *psi = *omega = 0.0;
        return 0;
    }
    double R[3];
    for (int i = 0; i < 3; ++i) R[i] = sqrt(dot3(a[i], a[i]));
    double h = dot3(a[0], nf);
    double rmin = fmin(R[0], fmin(R[1], R[2])), rmax = fmax(R[0], fmax(R[1], R[2]));
    /* Away from the plane and the corners the solid angle takes Van Oosterom and Strackee's
     * one-atan2 form; near them, the edge sum below, which does not cancel there, with h and the d_e
     * from the edges' perpendiculars (from their nearer ends: the same bits for both triangles of an
     * edge, as in the cage faces' fix-up and torch's _near_distances). */
    int far = fabs(h) >= GC_PERPENDICULAR_PLANE_RATIO * rmin && fabs(h) > tol && rmin >= GC_PERPENDICULAR_VERTEX_RATIO * rmax;
    double d[3], I[3], beta = 0.0;
    if (far) {
        for (int e = 0; e < 3; ++e) d[e] = dot3(a[(e + 1) % 3], eout + 3 * e);
    } else {
        double best = INFINITY;
        for (int e = 0; e < 3; ++e) {
            int j = (e + 1) % 3, k = (e + 2) % 3;
            const double *u = edir + 3 * e;
            double m[3];
            for (int c = 0; c < 3; ++c) m[c] = R[j] < R[k] ? a[j][c] : (R[k] < R[j] ? a[k][c] : 0.5 * (a[j][c] + a[k][c]));
            double mu = dot3(m, u), w[3] = {m[0] - mu * u[0], m[1] - mu * u[1], m[2] - mu * u[2]};
            d[e] = dot3(w, eout + 3 * e);
            double w2 = dot3(w, w);
            if (w2 < best) {
                best = w2;
                h = dot3(w, nf);
            }
        }
    }
    double habs = fabs(h);
    int on_plane = habs <= tol, inside = 1;
    double l_j[3], l_k[3], R_j[3], R_k[3], R0sq[3];
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        const double *u = edir + 3 * e;
        l_j[e] = dot3(a[j], u), l_k[e] = dot3(a[k], u), R_j[e] = R[j], R_k[e] = R[k];
        R0sq[e] = d[e] * d[e] + h * h;
        I[e] = log(tc_edge_log_arg(l_j[e], l_k[e], R[j], R[k], R0sq[e]));
        inside &= d[e] >= -tol;
    }
    if (!far) beta = edge_angle_sum(d, l_j, l_k, R_j, R_k, R0sq, habs);
    if (far) {
        double c12[3];
        cross3(a[1], a[2], c12);
        double den = R[0] * R[1] * R[2] + dot3(a[0], a[1]) * R[2] + dot3(a[0], a[2]) * R[1] + dot3(a[1], a[2]) * R[0];
        beta = 2.0 * atan2(dot3(a[0], c12), den); /* already signed like h */
        beta = h >= 0 ? beta : -beta;
    }
    /* On the face: its principal value, no solid angle. On its plane off the face the solid angle is
     * kept: it is 0 exactly in the plane, but of order one near an edge within the tolerance (the
     * fan of a planar quad seen by a point just off its boundary lost 3e-2 of partition of unity
     * when every in-plane point got 0, as in triangle_integrals' on_face). */
    int on_face = on_plane && inside;
    double om = on_face ? 0.0 : (h >= 0 ? beta : -beta);
    face_finish(h, om, on_face, d, I, ell, eout, gbary, two_area, phi, psi, alpha);
    *omega = om;
    if (tc_thin_face(a, two_area)) { /* a thin face seen from a few widths: the swept form */
        double ph[3];
        tc_thin_green(a, h, two_area, ph, psi, omega);
        if (phi)
            for (int i = 0; i < 3; ++i) phi[i] = ph[i];
    }
    return on_face;
}

/* The per-face constants tc_tri_green expects, for a triangle with corners a (any common origin):
 * nf (3), ell (3), edir, eout, gbary (3, 3); returns twice the area (0 for a degenerate triangle,
 * whose constants are then finite placeholders and its integrals zero). */
double tc_tri_frame(const double a[3][3], double *nf, double *ell, double *edir, double *eout, double *gbary) {
    double E[3][3], cr[3];
    for (int i = 0; i < 3; ++i) { /* the edge opposite corner i, p_{i+1} -> p_{i+2} */
        const double *pj = a[(i + 1) % 3], *pk = a[(i + 2) % 3];
        for (int c = 0; c < 3; ++c) E[i][c] = pk[c] - pj[c];
        ell[i] = sqrt(dot3(E[i], E[i]));
    }
    /* 2 A n = E_{i+1} x E_{i+2} for every i: the two shorter edges (a needle's two long edges
     * would leave its normal known to eps / width only). */
    int lo = ell[0] >= ell[1] && ell[0] >= ell[2] ? 0 : (ell[1] >= ell[2] ? 1 : 2);
    cross3(E[(lo + 1) % 3], E[(lo + 2) % 3], cr);
    double two_area = sqrt(dot3(cr, cr));
    for (int c = 0; c < 3; ++c) nf[c] = two_area > 0 ? cr[c] / two_area : (c == 2 ? 1.0 : 0.0);
    for (int i = 0; i < 3; ++i) {
        for (int c = 0; c < 3; ++c) edir[3 * i + c] = ell[i] > 0 ? E[i][c] / ell[i] : 0.0;
        cross3(edir + 3 * i, nf, eout + 3 * i);
        for (int c = 0; c < 3; ++c) gbary[3 * i + c] = two_area > 0 ? -eout[3 * i + c] * ell[i] / two_area : 0.0;
    }
    return two_area;
}

/*
 * Layouts: Pv (3, V) vertices; tri (3, T) int32 corners; edges (2, E) int32 unique edges and eu
 * (3, E) their unit directions; fe (3, T) int32 the edge opposite each corner; nrm (T, 3) unit
 * normals; two_area (T,); ell (T, 3) length of the edge opposite each corner; edir, eout, gbary
 * (T, 3, 3) its unit direction p_{i+1} -> p_{i+2}, outward in-plane normal, and the in-plane gradient
 * of corner i's hat function; X (n, 3). Outputs PHI (n, V), PSI (n, T). With ONF (n,) int32 and
 * AL (n, 3) given (not NULL), the faces are part of a larger cage: PHI keeps the principal values,
 * ONF gets the first face a point lies on (or -1) and AL the point's barycentric coordinates there,
 * and the caller adds the jump; without them, the jump is added here (a closed triangle cage).
 *
 * Per point, plain loops that the compiler vectorises (gathers, libmvec's log and atan2): one over
 * vertices (corner offsets, distances), one over unique edges (the edge integrals, shared by an
 * edge's two faces), one over faces for h, the d_e and the Van Oosterom-Strackee solid angle, a
 * scalar fix-up of the few faces near whose plane the point lies (edge-sum solid angle, points on
 * the cage, degenerate faces), one over faces for psi and the three corner terms, and a scatter of
 * those into phi. The corner terms use per-face constants folded once per call:
 * alpha_i = d_i ell_i / 2A and h g_i . K = h sum_e M_ie I_e with M_ie = -g_i . m_e.
 */

/* Per-face constants, structure of arrays (index [k * T + f]). */
enum { FC_N = 0, FC_O = 3, FC_C = 12, FC_M = 15, FC_S = 24, FC_THR = 25, FC_FAR = 26, FC_K = 27 };

/* Fold the per-face constants into g->fc and list the thin faces in g->thin (allocated here;
 * tc_gc_free releases them). Returns 0 when they could not be allocated (g->fc and g->thin NULL,
 * no thin faces): the caller marks its outputs NaN, which the glue reports as a MemoryError. */
int tc_gc_prepare(gc_tables *g) {
    long T = g->T;
    const double inv4pi = 1.0 / FOUR_PI;
    double *fc = (double *)malloc(sizeof(double) * FC_K * (size_t)(T > 0 ? T : 1));
    g->thin = (long *)malloc(sizeof(long) * (size_t)(T > 0 ? T : 1));
    g->nthin = 0;
    if (fc == NULL || g->thin == NULL) {
        free(fc);
        free(g->thin);
        g->fc = NULL;
        g->thin = NULL;
        return 0;
    }
    for (long f = 0; f < T; ++f) {
        const double *eout = g->eout + 9 * f, *gbary = g->gbary + 9 * f, two_area = g->two_area[f];
        int live = two_area > 0;
        for (int c = 0; c < 3; ++c) fc[(FC_N + c) * T + f] = g->nrm[3 * f + c];
        for (int e = 0; e < 9; ++e) fc[(FC_O + e) * T + f] = eout[e];
        for (int i = 0; i < 3; ++i) {
            fc[(FC_C + i) * T + f] = live ? g->ell[3 * f + i] / two_area * inv4pi : 0.0;
            for (int e = 0; e < 3; ++e)
                fc[(FC_M + 3 * i + e) * T + f] = live ? -dot3(gbary + 3 * i, eout + 3 * e) * inv4pi : 0.0;
        }
        fc[FC_S * T + f] = live ? inv4pi : 0.0;         /* psi's scale: degenerate faces integrate to nothing */
        fc[FC_THR * T + f] = live ? GC_PERPENDICULAR_PLANE_RATIO : -1.0; /* ... and always go to the fix-up */
        /* the far-field rule from this squared distance of the nearest corner (never without a rule) */
        double L = g->Q > 0 ? g->longest[f] : 0.0;
        fc[FC_FAR * T + f] = live && L > 0 ? (g->far_c * L) * (g->far_c * L) : INFINITY;
    }
    g->fc = fc;
    /* Faces THIN_ASPECT times longer than wide: their pairs may take the swept form. */
    for (long f = 0; f < T; ++f) {
        double L2 = 0.0;
        for (int i = 0; i < 3; ++i) L2 = fmax(L2, g->ell[3 * f + i] * g->ell[3 * f + i]);
        if (g->two_area[f] > 0 && L2 > 0.5 * TC_THIN_ASPECT * g->two_area[f]) g->thin[g->nthin++] = f;
    }
    return 1;
}

void tc_gc_free(gc_tables *g) {
    free(g->fc);
    free(g->thin);
    g->fc = NULL;
    g->thin = NULL;
}

/* ---- Faces seen from far: a Gauss rule (torchcage/families/green/far_triangle.py derives it) ---- */

int tc_far_pair(const gc_tables *g, long f, const double *R) {
    double rmin = R[0] < R[1] ? R[0] : R[1]; /* (as tc_gc_point's face pass decides) */
    rmin = rmin < R[2] ? rmin : R[2];
    return rmin * rmin >= g->fc[FC_FAR * g->T + f];
}

void tc_far_face(const gc_tables *g, long f, const double *x, double h, double *phi, double *psi, double *omega,
                 double *K, double *gom, double *gK) {
    const long Q = g->Q;
    const double *nodes = g->far_nodes + 3 * Q * f, *w = g->far_w + Q * f, *n = g->nrm + 3 * f;
    double s1 = 0.0, s3 = 0.0, a3[3] = {0.0, 0.0, 0.0}, b3[3] = {0.0, 0.0, 0.0};
    double a5[3] = {0.0, 0.0, 0.0}, aa5[9] = {0.0};
    for (long q = 0; q < Q; ++q) {
        double a[3] = {nodes[3 * q] - x[0], nodes[3 * q + 1] - x[1], nodes[3 * q + 2] - x[2]};
        double r2 = dot3(a, a), ir = 1.0 / sqrt(r2), w1 = w[q] * ir, w3 = w1 * ir * ir;
        const double *bq = g->far_bary + 3 * q;
        s1 += w1;
        s3 += w3;
        for (int c = 0; c < 3; ++c) a3[c] += w3 * a[c], b3[c] += w3 * bq[c];
        if (gom) {
            double w5 = w3 * ir * ir;
            for (int c = 0; c < 3; ++c) {
                a5[c] += w5 * a[c];
                for (int d = 0; d < 3; ++d) aa5[3 * c + d] += w5 * a[c] * a[d];
            }
        }
    }
    double om = h * s3;
    *omega = om;
    *psi = s1 / FOUR_PI;
    if (phi)
        for (int i = 0; i < 3; ++i) phi[i] = h * b3[i] / FOUR_PI;
    if (K)
        for (int c = 0; c < 3; ++c) K[c] = a3[c] - om * n[c];
    if (gom) {
        for (int c = 0; c < 3; ++c) gom[c] = 3.0 * h * a5[c] - s3 * n[c];
        for (int c = 0; c < 3; ++c)
            for (int d = 0; d < 3; ++d)
                gK[3 * c + d] = (n[c] * n[d] - (c == d ? 1.0 : 0.0)) * s3 + 3.0 * (aa5[3 * c + d] - n[c] * h * a5[d]);
    }
}

/* Face f (not degenerate) seen from a point near its plane or much nearer one corner than the
 * others (corner offsets a, distances R): d (3) and h again from each edge's perpendicular w_e (from
 * its nearer end, or its midpoint when both are as near): the same bits for both faces of an edge
 * (the two run it in opposite directions, u' = -u exactly), so that coplanar neighbours split their
 * solid angle without a gap near it; h from the nearest edge's w (torch: _edge_perpendicular). Sets
 * the solid angle om by the edge sum (which does not cancel near the plane); on the face (returns 1)
 * om = 0: the principal value (on its plane off the face the solid angle is kept: near an edge it is
 * of order 1 even where |h| <= tol). */
static inline int gc_near_face(const gc_tables *g, long f, const double a[3][3], const double *R, double tol,
                               double *d, double *h_out, double *om) {
    const double *ed = g->edir + 9 * f, *O = g->eout + 9 * f, *n = g->nrm + 3 * f;
    double h = 0.0, best = INFINITY;
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        const double *u = ed + 3 * e;
        double m[3] = {0.5 * (a[j][0] + a[k][0]), 0.5 * (a[j][1] + a[k][1]), 0.5 * (a[j][2] + a[k][2])};
        if (R[j] < R[k]) {
            m[0] = a[j][0], m[1] = a[j][1], m[2] = a[j][2];
        } else if (R[k] < R[j]) {
            m[0] = a[k][0], m[1] = a[k][1], m[2] = a[k][2];
        }
        double mu = m[0] * u[0] + m[1] * u[1] + m[2] * u[2];
        double w[3] = {m[0] - mu * u[0], m[1] - mu * u[1], m[2] - mu * u[2]};
        d[e] = w[0] * O[3 * e] + w[1] * O[3 * e + 1] + w[2] * O[3 * e + 2];
        double w2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
        if (w2 < best) {
            best = w2;
            h = w[0] * n[0] + w[1] * n[1] + w[2] * n[2];
        }
    }
    *h_out = h;
    double habs = fabs(h), beta = 0.0;
    if (habs <= tol && d[0] >= -tol && d[1] >= -tol && d[2] >= -tol) {
        *om = 0.0;
        return 1;
    }
    double l_j[3], l_k[3], R_j[3], R_k[3], R0sq[3];
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        const double *u = ed + 3 * e;
        l_j[e] = a[j][0] * u[0] + a[j][1] * u[1] + a[j][2] * u[2];
        l_k[e] = a[k][0] * u[0] + a[k][1] * u[1] + a[k][2] * u[2];
        R_j[e] = R[j], R_k[e] = R[k], R0sq[e] = d[e] * d[e] + h * h;
    }
    beta = edge_angle_sum(d, l_j, l_k, R_j, R_k, R0sq, habs);
    *om = h >= 0 ? beta : -beta;
    return 0;
}

/* A point on face f (signed edge distances d (3)): its barycentric coordinates there (3,). */
static inline void gc_on_alpha(const gc_tables *g, long f, const double *d, double *on_alpha) {
    double sum = 0.0;
    for (int i = 0; i < 3; ++i) {
        double al = d[i] * g->ell[3 * f + i] / g->two_area[f];
        on_alpha[i] = al > 0 ? al : 0.0;
        sum += on_alpha[i];
    }
    for (int i = 0; i < 3; ++i) on_alpha[i] /= sum;
}

/* Doubles of workspace tc_gc_point needs. */
size_t tc_gc_workspace(const gc_tables *g) { return 4 * (size_t)g->V + (size_t)g->E + 6 * (size_t)g->T; }

/* The views of the tables g that tc_gc_point and gc_block read (sizes, vertex and face columns). */
#define GC_TABLE_VIEWS(g)                                                                                       \
    const long V = (g)->V, T = (g)->T, E = (g)->E;                                                               \
    const double *Pv = (g)->Pv, *eu = (g)->eu, *fc = (g)->fc, *two_area = (g)->two_area;                        \
    const int *t0 = (g)->tri, *t1 = t0 + T, *t2 = t1 + T, *e0 = (g)->edges, *e1 = e0 + E;                        \
    const int *f0 = (g)->fe, *f1 = f0 + T, *f2 = f1 + T;                                                         \
    const double *Nx = fc + FC_N * T, *Ny = Nx + T, *Nz = Ny + T, *O = fc + FC_O * T, *Cc = fc + FC_C * T;        \
    const double *M = fc + FC_M * T, *S = fc + FC_S * T, *THR = fc + FC_THR * T, *FAR2 = fc + FC_FAR * T;        \
    const double inv4pi = 1.0 / FOUR_PI

/*
 * The Green integrals of all faces seen from the point x: psi (T,) and each face's corner terms
 * P (3, T) (index [i * T + f]: corner i's share of phi, principal values on the cage) and solid
 * angle OM (T,). ws: tc_gc_workspace(g) doubles. Returns the first face x lies on (or -1), with
 * x's barycentric coordinates there in on_alpha (3,).
 */
long tc_gc_point(const gc_tables *g, const double *x, double tol, double *ws, double *psi, double *P, double *OM,
                 double *on_alpha) {
    GC_TABLE_VIEWS(g);
    double *Ax = ws, *Ay = Ax + V, *Az = Ay + V, *RA = Az + V, *IE = RA + V;
    double *H = IE + E, *D0 = H + T, *D1 = D0 + T, *D2 = D1 + T, *FL = D2 + T, *FA = FL + T;
    double *P0 = P, *P1 = P + T, *P2 = P + 2 * T;
#pragma omp simd
    for (long v = 0; v < V; ++v) {
        double ax = Pv[v] - x[0], ay = Pv[V + v] - x[1], az = Pv[2 * V + v] - x[2];
        Ax[v] = ax;
        Ay[v] = ay;
        Az[v] = az;
        RA[v] = sqrt(ax * ax + ay * ay + az * az);
    }
    /* Edge integrals (the logs in a loop of their own, vectorised with libmvec). */
#pragma omp simd
    for (long q = 0; q < E; ++q) {
        int j = e0[q], k = e1[q];
        double ux = eu[q], uy = eu[E + q], uz = eu[2 * E + q];
        double l_j = Ax[j] * ux + Ay[j] * uy + Az[j] * uz, l_k = Ax[k] * ux + Ay[k] * uy + Az[k] * uz;
        double cx = Ay[j] * uz - Az[j] * uy, cy = Az[j] * ux - Ax[j] * uz, cz = Ax[j] * uy - Ay[j] * ux;
        IE[q] = tc_edge_log_arg(l_j, l_k, RA[j], RA[k], cx * cx + cy * cy + cz * cz);
    }
#pragma omp simd
    for (long q = 0; q < E; ++q) IE[q] = log(IE[q]);
    /* h, the d_e, the solid angle away from the plane, and which faces need the fix-up. */
#pragma omp simd
    for (long f = 0; f < T; ++f) {
        int i0 = t0[f], i1 = t1[f], i2 = t2[f];
        double a0x = Ax[i0], a0y = Ay[i0], a0z = Az[i0], a1x = Ax[i1], a1y = Ay[i1], a1z = Az[i1];
        double a2x = Ax[i2], a2y = Ay[i2], a2z = Az[i2], R0 = RA[i0], R1 = RA[i1], R2 = RA[i2];
        double h = a0x * Nx[f] + a0y * Ny[f] + a0z * Nz[f];
        H[f] = h;
        D0[f] = a1x * O[f] + a1y * O[T + f] + a1z * O[2 * T + f];
        D1[f] = a2x * O[3 * T + f] + a2y * O[4 * T + f] + a2z * O[5 * T + f];
        D2[f] = a0x * O[6 * T + f] + a0y * O[7 * T + f] + a0z * O[8 * T + f];
        double c12x = a1y * a2z - a1z * a2y, c12y = a1z * a2x - a1x * a2z, c12z = a1x * a2y - a1y * a2x;
        double den = R0 * R1 * R2 + (a0x * a1x + a0y * a1y + a0z * a1z) * R2 +
                     (a0x * a2x + a0y * a2y + a0z * a2z) * R1 + (a1x * a2x + a1y * a2y + a1z * a2z) * R0;
        OM[f] = 2.0 * atan2(a0x * c12x + a0y * c12y + a0z * c12z, den);
        double rmin = R0 < R1 ? R0 : R1;
        rmin = rmin < R2 ? rmin : R2;
        double rmax = R0 > R1 ? R0 : R1;
        rmax = rmax > R2 ? rmax : R2;
        double ha = h >= 0 ? h : -h;
        /* Near its plane, or much nearer one corner than the others (the one-atan2 form loses
         * digits there too: 5e-9 of partition of unity at 3e-14 from a sliver's apex): edge sum. */
        FL[f] = (ha < THR[f] * rmin || ha <= tol || THR[f] < 0 || rmin < GC_PERPENDICULAR_VERTEX_RATIO * rmax) ? 1.0 : 0.0;
        FA[f] = rmin * rmin >= FAR2[f] ? 1.0 : 0.0; /* seen from far: the Gauss rule below */
    }
    long on_face = -1;
    on_alpha[0] = on_alpha[1] = on_alpha[2] = 0.0;
    for (long f = 0; f < T; ++f) {
        if (FL[f] == 0.0) continue;
        if (!(two_area[f] > 0)) { /* degenerate: its constants are zero, its solid angle too */
            OM[f] = 0.0;
            continue;
        }
        const int c3[3] = {t0[f], t1[f], t2[f]};
        double a[3][3], R[3], d[3], h, om;
        for (int i = 0; i < 3; ++i) a[i][0] = Ax[c3[i]], a[i][1] = Ay[c3[i]], a[i][2] = Az[c3[i]], R[i] = RA[c3[i]];
        int on = gc_near_face(g, f, a, R, tol, d, &h, &om);
        D0[f] = d[0];
        D1[f] = d[1];
        D2[f] = d[2];
        H[f] = h;
        OM[f] = om;
        if (on && (on_face < 0 || two_area[f] > two_area[on_face])) { /* the largest face: best conditioned */
            on_face = f;
            gc_on_alpha(g, f, d, on_alpha);
        }
    }
    /* psi and the corner terms; on a face's plane (|h| <= tol) h K is dropped, and a d_e = 0 (the
     * point on an edge line) drops that edge's integral. */
#pragma omp simd
    for (long f = 0; f < T; ++f) {
        double I0 = IE[f0[f]], I1 = IE[f1[f]], I2 = IE[f2[f]], h = H[f], om = OM[f];
        double d0 = D0[f], d1 = D1[f], d2 = D2[f];
        double q0 = d0 * I0, q1 = d1 * I1, q2 = d2 * I2;
        double dI = (d0 != 0 ? q0 : 0.0) + (d1 != 0 ? q1 : 0.0) + (d2 != 0 ? q2 : 0.0);
        psi[f] = S[f] * dI - h * om * inv4pi;
        double ha = h >= 0 ? h : -h, hk = ha <= tol ? 0.0 : h;
        const double *m = M + f;
        P0[f] = Cc[f] * d0 * om + hk * (m[0] * I0 + m[T] * I1 + m[2 * T] * I2);
        P1[f] = Cc[T + f] * d1 * om + hk * (m[3 * T] * I0 + m[4 * T] * I1 + m[5 * T] * I2);
        P2[f] = Cc[2 * T + f] * d2 * om + hk * (m[6 * T] * I0 + m[7 * T] * I1 + m[8 * T] * I2);
    }
    for (long q = 0; q < g->nthin; ++q) { /* thin faces seen from a few widths: the swept form */
        long f = g->thin[q];
        const int c3[3] = {t0[f], t1[f], t2[f]};
        double a[3][3], ph[3];
        for (int i = 0; i < 3; ++i) a[i][0] = Ax[c3[i]], a[i][1] = Ay[c3[i]], a[i][2] = Az[c3[i]];
        if (!tc_thin_face(a, two_area[f])) continue;
        tc_thin_green(a, H[f], two_area[f], ph, psi + f, OM + f);
        P0[f] = ph[0], P1[f] = ph[1], P2[f] = ph[2];
    }
    if (g->Q > 0) /* faces seen from far: the Gauss rule (the closed forms lose eps (r / edge)^2) */
        for (long f = 0; f < T; ++f) {
            if (FA[f] == 0.0) continue;
            double ph[3], h = Ax[t0[f]] * Nx[f] + Ay[t0[f]] * Ny[f] + Az[t0[f]] * Nz[f];
            tc_far_face(g, f, x, h, ph, psi + f, OM + f, NULL, NULL, NULL);
            P0[f] = ph[0], P1[f] = ph[1], P2[f] = ph[2];
        }
    return on_face;
}

/*
 * GC_LANES points at once (gc_block): the same forms as tc_gc_point, vectorised across the points
 * rather than the faces, so that every load is contiguous (arrays [vertex | edge | face][lane]) and
 * the per-face constants are broadcast: no gathers. Per face, one vector pass gives h, the d_e, the
 * one-atan2 solid angle and which lanes need a careful form; those lanes (near the face's plane or
 * a corner, on the face, degenerate faces, thin faces seen from a few widths, faces seen from far)
 * take tc_gc_point's own code for that pair (gc_near_face, tc_thin_green, tc_far_face), then one
 * vector pass gives psi and the corner terms, in tc_gc_point's order.
 */
#ifndef GC_LANES
#define GC_LANES 8
#endif
#define GL GC_LANES

/* Doubles of workspace gc_block needs: corner offsets and distances (4 V), phi (V), the edge
 * integrals (E) and psi (T), each GL lanes wide. */
static size_t gc_block_workspace(const gc_tables *g) {
    return (size_t)GL * (5 * (size_t)g->V + (size_t)g->E + 3 * (size_t)g->T);
}

/* tc_far_face (phi, psi, omega) of face f for the lanes with fa[l] != 0 (points x0, x1, x2 (GL,),
 * first corner's offsets a0x, a0y, a0z (GL,)): the same sums in the same order, across the lanes. */
static inline void gc_far_lanes(const gc_tables *g, long f, const double *x0, const double *x1, const double *x2,
                                const double *a0x, const double *a0y, const double *a0z, const double *fa,
                                double *ps, double *om, double *p0, double *p1, double *p2) {
    const long Q = g->Q;
    const double *nodes = g->far_nodes + 3 * Q * f, *w = g->far_w + Q * f, *n = g->nrm + 3 * f;
    double s1[GL], s3[GL], b0[GL], b1[GL], b2[GL];
    for (int l = 0; l < GL; ++l) s1[l] = s3[l] = b0[l] = b1[l] = b2[l] = 0.0;
    for (long q = 0; q < Q; ++q) {
        const double nqx = nodes[3 * q], nqy = nodes[3 * q + 1], nqz = nodes[3 * q + 2], wq = w[q];
        const double *bq = g->far_bary + 3 * q;
        const double bq0 = bq[0], bq1 = bq[1], bq2 = bq[2];
#pragma omp simd
        for (int l = 0; l < GL; ++l) {
            double ax = nqx - x0[l], ay = nqy - x1[l], az = nqz - x2[l];
            double r2 = ax * ax + ay * ay + az * az, ir = 1.0 / sqrt(r2), w1 = wq * ir, w3 = w1 * ir * ir;
            s1[l] += w1;
            s3[l] += w3;
            b0[l] += w3 * bq0;
            b1[l] += w3 * bq1;
            b2[l] += w3 * bq2;
        }
    }
#pragma omp simd
    for (int l = 0; l < GL; ++l) {
        if (fa[l] == 0.0) continue;
        double h = a0x[l] * n[0] + a0y[l] * n[1] + a0z[l] * n[2];
        om[l] = h * s3[l];
        ps[l] = s1[l] / FOUR_PI;
        p0[l] = h * b0[l] / FOUR_PI;
        p1[l] = h * b1[l] / FOUR_PI;
        p2[l] = h * b2[l] / FOUR_PI;
    }
}

/* dst[i] = src[stride * i] for i < n; with stream, past the caches (non-temporal stores: a large
 * output, written once, is not first read in; the caller fences). */
static inline void gc_copy_out(double *dst, const double *src, long stride, long n, int stream) {
#ifdef GC_STREAM
    if (stream) {
        for (long i = 0; i < n; ++i) {
            long long bits;
            memcpy(&bits, src + stride * i, sizeof bits);
            _mm_stream_si64((long long *)(dst + i), bits);
        }
        return;
    }
#else
    (void)stream;
#endif
    for (long i = 0; i < n; ++i) dst[i] = src[stride * i];
}

/* The Green coordinates of cnt <= GL points X (cnt, 3): rows PHI (cnt, V) and PSI (cnt, T), with
 * tc_gc_point's forms (with ONF, AL (cnt,), (cnt, 3), or the jump added here). Each lane's results
 * depend on its point alone, whatever the others and cnt. thin: 1 for the faces in g->thin (T,).
 * ws: gc_block_workspace(g) doubles. */
#if defined(__x86_64__) && defined(__AVX2__) && defined(TC_LIBMVEC) && defined(__GNUC__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "default")))
#endif
static void gc_block(const gc_tables *g, const unsigned char *thin, const double *X, int cnt, double tol, double *ws,
                     int stream, double *PHI, double *PSI, int *ONF, double *AL) {
    GC_TABLE_VIEWS(g);
    double *AX = ws, *AY = AX + GL * V, *AZ = AY + GL * V, *RA = AZ + GL * V, *PH = RA + GL * V;
    double *IE = PH + GL * V, *PS = IE + GL * E, *OA = PS + GL * T, *DEN = OA + GL * T;
    double x0[GL], x1[GL], x2[GL], osum[GL], oal[GL][3];
    long onf[GL];
    for (int l = 0; l < GL; ++l) {
        const double *xl = X + 3 * (l < cnt ? l : cnt - 1); /* (lanes past cnt repeat the last point) */
        x0[l] = xl[0], x1[l] = xl[1], x2[l] = xl[2];
        osum[l] = 0.0, onf[l] = -1, oal[l][0] = oal[l][1] = oal[l][2] = 0.0;
    }
    for (long v = 0; v < V; ++v) {
        const double px = Pv[v], py = Pv[V + v], pz = Pv[2 * V + v];
        double *ax = AX + GL * v, *ay = AY + GL * v, *az = AZ + GL * v, *ra = RA + GL * v, *ph = PH + GL * v;
#pragma omp simd
        for (int l = 0; l < GL; ++l) {
            double dx = px - x0[l], dy = py - x1[l], dz = pz - x2[l];
            ax[l] = dx, ay[l] = dy, az[l] = dz, ph[l] = 0.0;
            ra[l] = sqrt(dx * dx + dy * dy + dz * dz);
        }
    }
    /* Edge integrals, shared by an edge's two faces. */
    for (long q = 0; q < E; ++q) {
        const long j = GL * (long)e0[q], k = GL * (long)e1[q];
        const double ux = eu[q], uy = eu[E + q], uz = eu[2 * E + q];
        double *ie = IE + GL * q;
#pragma omp simd
        for (int l = 0; l < GL; ++l) {
            double ajx = AX[j + l], ajy = AY[j + l], ajz = AZ[j + l], akx = AX[k + l], aky = AY[k + l], akz = AZ[k + l];
            double l_j = ajx * ux + ajy * uy + ajz * uz, l_k = akx * ux + aky * uy + akz * uz;
            double cx = ajy * uz - ajz * uy, cy = ajz * ux - ajx * uz, cz = ajx * uy - ajy * ux;
            ie[l] = tc_edge_log_arg(l_j, l_k, RA[j + l], RA[k + l], cx * cx + cy * cy + cz * cz);
        }
    }
    /* (the logs and the atan2 below in loops of their own: long, contiguous, libmvec's vector forms) */
#pragma omp simd
    for (long q = 0; q < GL * E; ++q) IE[q] = log(IE[q]);
    /* The one-atan2 solid angle's arguments, then the angles. */
    for (long f = 0; f < T; ++f) {
        const long i0 = GL * (long)t0[f], i1 = GL * (long)t1[f], i2 = GL * (long)t2[f];
        double *num = OA + GL * f, *den = DEN + GL * f;
#pragma omp simd
        for (int l = 0; l < GL; ++l) {
            double a0x = AX[i0 + l], a0y = AY[i0 + l], a0z = AZ[i0 + l], a1x = AX[i1 + l], a1y = AY[i1 + l];
            double a1z = AZ[i1 + l], a2x = AX[i2 + l], a2y = AY[i2 + l], a2z = AZ[i2 + l];
            double R0 = RA[i0 + l], R1 = RA[i1 + l], R2 = RA[i2 + l];
            double c12x = a1y * a2z - a1z * a2y, c12y = a1z * a2x - a1x * a2z, c12z = a1x * a2y - a1y * a2x;
            den[l] = R0 * R1 * R2 + (a0x * a1x + a0y * a1y + a0z * a1z) * R2 +
                     (a0x * a2x + a0y * a2y + a0z * a2z) * R1 + (a1x * a2x + a1y * a2y + a1z * a2z) * R0;
            num[l] = a0x * c12x + a0y * c12y + a0z * c12z;
        }
    }
#pragma omp simd
    for (long q = 0; q < GL * T; ++q) OA[q] = 2.0 * atan2(OA[q], DEN[q]);
    for (long f = 0; f < T; ++f) {
        const long i0 = GL * (long)t0[f], i1 = GL * (long)t1[f], i2 = GL * (long)t2[f];
        const double nx = Nx[f], ny = Ny[f], nz = Nz[f], thr = THR[f], far2 = FAR2[f];
        const double o0 = O[f], o1 = O[T + f], o2 = O[2 * T + f], o3 = O[3 * T + f], o4 = O[4 * T + f];
        const double o5 = O[5 * T + f], o6 = O[6 * T + f], o7 = O[7 * T + f], o8 = O[8 * T + f];
        double hh[GL], d0[GL], d1[GL], d2[GL], om[GL], fl[GL], fa[GL], p0[GL], p1[GL], p2[GL], any = 0.0;
        const double *oa = OA + GL * f;
#pragma omp simd reduction(max : any)
        for (int l = 0; l < GL; ++l) {
            double a0x = AX[i0 + l], a0y = AY[i0 + l], a0z = AZ[i0 + l], a1x = AX[i1 + l], a1y = AY[i1 + l];
            double a1z = AZ[i1 + l], a2x = AX[i2 + l], a2y = AY[i2 + l], a2z = AZ[i2 + l];
            double R0 = RA[i0 + l], R1 = RA[i1 + l], R2 = RA[i2 + l];
            double h = a0x * nx + a0y * ny + a0z * nz;
            hh[l] = h;
            d0[l] = a1x * o0 + a1y * o1 + a1z * o2;
            d1[l] = a2x * o3 + a2y * o4 + a2z * o5;
            d2[l] = a0x * o6 + a0y * o7 + a0z * o8;
            om[l] = oa[l];
            double rmin = R0 < R1 ? R0 : R1;
            rmin = rmin < R2 ? rmin : R2;
            double rmax = R0 > R1 ? R0 : R1;
            rmax = rmax > R2 ? rmax : R2;
            double ha = h >= 0 ? h : -h;
            fl[l] = (ha < thr * rmin || ha <= tol || thr < 0 || rmin < GC_PERPENDICULAR_VERTEX_RATIO * rmax) ? 1.0 : 0.0;
            fa[l] = rmin * rmin >= far2 ? 1.0 : 0.0;
            double flag = fl[l] + fa[l];
            any = any > flag ? any : flag; /* (a max: no ordered sum across the lanes) */
        }
        if (any != 0.0) /* near the face's plane or a corner: tc_gc_point's fix-up */
            for (int l = 0; l < GL; ++l) {
                if (fl[l] == 0.0) continue;
                if (!(two_area[f] > 0)) {
                    om[l] = 0.0;
                    continue;
                }
                double a[3][3] = {{AX[i0 + l], AY[i0 + l], AZ[i0 + l]},
                                  {AX[i1 + l], AY[i1 + l], AZ[i1 + l]},
                                  {AX[i2 + l], AY[i2 + l], AZ[i2 + l]}};
                double R[3] = {RA[i0 + l], RA[i1 + l], RA[i2 + l]}, d[3];
                int on = gc_near_face(g, f, a, R, tol, d, hh + l, om + l);
                d0[l] = d[0], d1[l] = d[1], d2[l] = d[2];
                if (on && (onf[l] < 0 || two_area[f] > two_area[onf[l]])) {
                    onf[l] = f;
                    gc_on_alpha(g, f, d, oal[l]);
                }
            }
        const double *I0v = IE + GL * (long)f0[f], *I1v = IE + GL * (long)f1[f], *I2v = IE + GL * (long)f2[f];
        const double s = S[f], c0 = Cc[f], c1 = Cc[T + f], c2 = Cc[2 * T + f];
        const double m0 = M[f], m1 = M[T + f], m2 = M[2 * T + f], m3 = M[3 * T + f], m4 = M[4 * T + f];
        const double m5 = M[5 * T + f], m6 = M[6 * T + f], m7 = M[7 * T + f], m8 = M[8 * T + f];
        double *ps = PS + GL * f;
#pragma omp simd
        for (int l = 0; l < GL; ++l) {
            double I0 = I0v[l], I1 = I1v[l], I2 = I2v[l], h = hh[l], o = om[l];
            double q0 = d0[l] * I0, q1 = d1[l] * I1, q2 = d2[l] * I2;
            double dI = (d0[l] != 0 ? q0 : 0.0) + (d1[l] != 0 ? q1 : 0.0) + (d2[l] != 0 ? q2 : 0.0);
            ps[l] = s * dI - h * o * inv4pi;
            double ha = h >= 0 ? h : -h, hk = ha <= tol ? 0.0 : h;
            p0[l] = c0 * d0[l] * o + hk * (m0 * I0 + m1 * I1 + m2 * I2);
            p1[l] = c1 * d1[l] * o + hk * (m3 * I0 + m4 * I1 + m5 * I2);
            p2[l] = c2 * d2[l] * o + hk * (m6 * I0 + m7 * I1 + m8 * I2);
        }
        if (thin[f]) /* a thin face seen from a few widths: the swept form */
            for (int l = 0; l < GL; ++l) {
                double a[3][3] = {{AX[i0 + l], AY[i0 + l], AZ[i0 + l]},
                                  {AX[i1 + l], AY[i1 + l], AZ[i1 + l]},
                                  {AX[i2 + l], AY[i2 + l], AZ[i2 + l]}}, ph[3];
                if (!tc_thin_face(a, two_area[f])) continue;
                tc_thin_green(a, hh[l], two_area[f], ph, ps + l, om + l);
                p0[l] = ph[0], p1[l] = ph[1], p2[l] = ph[2];
            }
        if (any != 0.0 && g->Q > 0) { /* seen from far: the Gauss rule (tc_far_face's sums, lane by lane) */
            double nfar = 0.0;
            for (int l = 0; l < GL; ++l) nfar += fa[l];
            if (nfar != 0.0) gc_far_lanes(g, f, x0, x1, x2, AX + i0, AY + i0, AZ + i0, fa, ps, om, p0, p1, p2);
        }
#pragma omp simd
        for (int l = 0; l < GL; ++l) {
            PH[i0 + l] += p0[l];
            PH[i1 + l] += p1[l];
            PH[i2 + l] += p2[l];
            osum[l] += om[l];
        }
    }
    for (int l = 0; l < cnt; ++l) {
        if (ONF) {
            ONF[l] = (int)onf[l];
            for (int i = 0; i < 3; ++i) AL[3 * l + i] = oal[l][i];
        } else if (onf[l] >= 0) { /* the limit from inside: hat values with the jump weight */
            double jump = 1.0 - osum[l] / FOUR_PI;
            for (int i = 0; i < 3; ++i) PH[GL * (long)g->tri[i * T + onf[l]] + l] += jump * oal[l][i];
        }
        double *phi = PHI + l * V, *psi = PSI + l * T;
        gc_copy_out(phi, PH + l, GL, V, stream);
        gc_copy_out(psi, PS + l, GL, T, stream);
    }
}

/* The blocks of GL points of B cages with one topology: element b's tables gs[b] (prepared; thin:
 * its flags at thin + T b), points X + 3 n b, tolerance tol[b], rows PHI + V n b, PSI + T n b (ONF
 * + n b, AL + 3 n b). One parallel loop over every element's blocks; failed: every output NaN. */
static void gc3d_run(long B, const gc_tables *gs, const unsigned char *thin, const double *X, long n, const double *tol,
                     int nthreads, int failed, double *PHI, double *PSI, int *ONF, double *AL) {
    const long V = gs[0].V, T = gs[0].T;
    const long nb = (n + GL - 1) / GL; /* blocks of GL points per element (the last one shorter) */
    /* outputs past 32 MiB per element streamed, as for one cage (streaming a batch of small elements
     * as a whole measured slower: 8 x 5,000 points, 42 vertices, 47 against 31 ms in one process
     * alternated with the loop of single-cage calls) */
    const int stream = (double)n * (double)(V + T) > (double)(1 << 22);
#pragma omp parallel num_threads(nthreads)
    {
        double *buf = failed ? NULL : (double *)malloc(sizeof(double) * gc_block_workspace(&gs[0]));
        if (buf == NULL) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp for schedule(dynamic, 2)
        for (long i = 0; i < B * nb; ++i) {
            const long b = i / nb, p = GL * (i % nb);
            const int cnt = n - p < GL ? (int)(n - p) : GL;
            const long row = n * b + p;
            if (buf == NULL) continue;
            gc_block(&gs[b], thin + T * b, X + 3 * row, cnt, tol[b], buf, stream, PHI + row * V, PSI + row * T,
                     ONF && AL ? ONF + row : NULL, ONF && AL ? AL + 3 * row : NULL);
        }
#ifdef GC_STREAM
        _mm_sfence(); /* the streamed stores before this thread's part is read */
#endif
        free(buf);
    }
    if (failed) {
        for (long i = 0; i < B * n * V; ++i) PHI[i] = NAN;
        for (long i = 0; i < B * n * T; ++i) PSI[i] = NAN;
    }
}

/* Fold element b's tables (prepared: 0 when they could not be allocated) and its thin flags. */
static int gc_prepare_thin(gc_tables *g, unsigned char *thin) {
    if (!tc_gc_prepare(g)) return 0;
    for (long q = 0; q < g->nthin; ++q) thin[g->thin[q]] = 1;
    return 1;
}

void tc_gc3d(const double *Pv, long V, const int *tri, long T, const int *edges, long E, const double *eu,
             const int *fe, const double *nrm, const double *two_area, const double *ell, const double *edir,
             const double *eout, const double *gbary, const double *longest, const double *far_nodes,
             const double *far_w, const double *far_bary, long Q, double far_c, const double *X, long n, double tol,
             int nthreads, double *PHI, double *PSI, int *ONF, double *AL) {
    gc_tables g = {Pv,   V,    tri,  T,       edges,     E,    eu,       fe, nrm, two_area, ell, edir, eout,
                   gbary, NULL, NULL, 0,       longest,   far_nodes, far_w, far_bary, Q, far_c};
    unsigned char *thin = (unsigned char *)calloc((size_t)(T > 0 ? T : 1), 1);
    int failed = thin == NULL || !gc_prepare_thin(&g, thin); /* (a workspace not allocated: the glue raises) */
    gc3d_run(1, &g, thin, X, n, &tol, nthreads, failed, PHI, PSI, ONF, AL);
    free(thin);
    tc_gc_free(&g);
}

/* tc_gc3d for B cages with one topology (tri, edges, fe shared): each per-cage table has a leading
 * batch axis (Pv (B, 3, V), eu (B, 3, E), nrm (B, T, 3) ..., far_nodes (B, T, Q, 3), far_w (B, T, Q);
 * far_bary is shared), X (B, n, 3), tol (B,), outputs PHI (B, n, V), PSI (B, n, T) (closed cages:
 * the jump is added here; with ONF (B, n) and AL (B, n, 3) given, the faces are part of larger cages,
 * as in tc_gc3d). Element by element the numbers of tc_gc3d. */
void tc_gc3d_batch(long B, const double *Pv, long V, const int *tri, long T, const int *edges, long E,
                   const double *eu, const int *fe, const double *nrm, const double *two_area, const double *ell,
                   const double *edir, const double *eout, const double *gbary, const double *longest,
                   const double *far_nodes, const double *far_w, const double *far_bary, long Q, double far_c,
                   const double *X, long n, const double *tol, int nthreads, double *PHI, double *PSI, int *ONF,
                   double *AL) {
    gc_tables *gs = (gc_tables *)calloc((size_t)(B > 0 ? B : 1), sizeof(gc_tables));
    unsigned char *thin = (unsigned char *)calloc((size_t)(B * T > 0 ? B * T : 1), 1);
    if (gs == NULL || thin == NULL) { /* every output NaN (the glue raises) */
        for (long i = 0; i < B * n * V; ++i) PHI[i] = NAN;
        for (long i = 0; i < B * n * T; ++i) PSI[i] = NAN;
        free(gs);
        free(thin);
        return;
    }
    int failed = 0;
    for (long b = 0; !failed && b < B; ++b) {
        gc_tables g = {Pv + 3 * V * b, V, tri, T, edges, E, eu + 3 * E * b, fe, nrm + 3 * T * b, two_area + T * b,
                       ell + 3 * T * b, edir + 9 * T * b, eout + 9 * T * b, gbary + 9 * T * b, NULL, NULL, 0,
                       longest + T * b, far_nodes + 3 * Q * T * b, far_w + Q * T * b, far_bary, Q, far_c};
        gs[b] = g;
        failed = !gc_prepare_thin(&gs[b], thin + T * b);
    }
    if (B > 0) gc3d_run(B, gs, thin, X, n, tol, nthreads, failed, PHI, PSI, ONF, AL);
    for (long b = 0; b < B; ++b) tc_gc_free(&gs[b]);
    free(gs);
    free(thin);
}
