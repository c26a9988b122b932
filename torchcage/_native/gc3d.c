/*
 * Native CPU kernel of torchcage's 3D Green coordinates (float64): the same closed forms as
 * torchcage/functional/_green3d.py (see its module docstring), one point per iteration (tc_gc_point,
 * also used by the QGC kernel), OpenMP over points. The tests check it against the torch kernel.
 */
#define _GNU_SOURCE
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define FOUR_PI 12.566370614359172953850573533118
#define GC_PERPENDICULAR_PLANE_RATIO 0.01 /* pairs closer to a face plane than this x min R: edge-sum solid angle */
#define GC_PERPENDICULAR_VERTEX_RATIO 1e-3 /* pairs nearer a corner than this x the farthest corner: edge-sum solid angle */

#include "native.h"

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector log and atan2 (libmvec) in the plain loops below. */
__attribute__((simd("notinbranch"))) double log(double);
__attribute__((simd("notinbranch"))) double atan2(double, double);
#endif

/* One edge's term of the solid angle's edge sum (no cancellation near the face's plane): d the
 * foot point's signed distance to the edge line, l_j, l_k, R_j, R_k as in tc_edge_log_arg, R0sq =
 * d^2 + h^2, habs = |h|. */
static inline double edge_angle(double d, double l_j, double l_k, double R_j, double R_k, double R0sq, double habs) {
    return atan2(d * l_k, R0sq + habs * R_k) - atan2(d * l_j, R0sq + habs * R_j);
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
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        const double *u = edir + 3 * e;
        double l_j = dot3(a[j], u), l_k = dot3(a[k], u), R0sq = d[e] * d[e] + h * h;
        if (!far) beta += edge_angle(d[e], l_j, l_k, R[j], R[k], R0sq, habs);
        I[e] = log(tc_edge_log_arg(l_j, l_k, R[j], R[k], R0sq));
        inside &= d[e] >= -tol;
    }
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
enum { FC_N = 0, FC_O = 3, FC_C = 12, FC_M = 15, FC_S = 24, FC_THR = 25, FC_K = 26 };

/* Fold the per-face constants into g->fc (allocated here; tc_gc_free releases it). */
void tc_gc_prepare(gc_tables *g) {
    long T = g->T;
    const double inv4pi = 1.0 / FOUR_PI;
    double *fc = (double *)malloc(sizeof(double) * FC_K * (size_t)T);
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
    }
    g->fc = fc;
}

void tc_gc_free(gc_tables *g) {
    free(g->fc);
    g->fc = NULL;
}

/* Doubles of workspace tc_gc_point needs. */
size_t tc_gc_workspace(const gc_tables *g) { return 4 * (size_t)g->V + (size_t)g->E + 5 * (size_t)g->T; }

/*
 * The Green integrals of all faces seen from the point x: psi (T,) and each face's corner terms
 * P (3, T) (index [i * T + f]: corner i's share of phi, principal values on the cage) and solid
 * angle OM (T,). ws: tc_gc_workspace(g) doubles. Returns the first face x lies on (or -1), with
 * x's barycentric coordinates there in on_alpha (3,).
 */
long tc_gc_point(const gc_tables *g, const double *x, double tol, double *ws, double *psi, double *P, double *OM,
                 double *on_alpha) {
    const long V = g->V, T = g->T, E = g->E;
    const double *Pv = g->Pv, *eu = g->eu, *fc = g->fc, *two_area = g->two_area;
    const int *t0 = g->tri, *t1 = t0 + T, *t2 = t1 + T, *e0 = g->edges, *e1 = e0 + E;
    const int *f0 = g->fe, *f1 = f0 + T, *f2 = f1 + T;
    const double *Nx = fc + FC_N * T, *Ny = Nx + T, *Nz = Ny + T, *O = fc + FC_O * T, *Cc = fc + FC_C * T;
    const double *M = fc + FC_M * T, *S = fc + FC_S * T, *THR = fc + FC_THR * T;
    const double inv4pi = 1.0 / FOUR_PI;
    double *Ax = ws, *Ay = Ax + V, *Az = Ay + V, *RA = Az + V, *IE = RA + V;
    double *H = IE + E, *D0 = H + T, *D1 = D0 + T, *D2 = D1 + T, *FL = D2 + T;
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
        const double *ed = g->edir + 9 * f;
        /* Near the plane, d_e and h again from each edge's perpendicular w_e (from its nearer end,
         * or its midpoint when both are as near): the same bits for both faces of an edge (the two
         * run it in opposite directions, u' = -u exactly), so that coplanar neighbours split their
         * solid angle without a gap near it; h from the nearest edge's w (torch: _edge_perpendicular). */
        double d[3], h = 0.0, best = INFINITY;
        for (int e = 0; e < 3; ++e) {
            int j = c3[(e + 1) % 3], k = c3[(e + 2) % 3];
            const double *u = ed + 3 * e;
            double m[3] = {0.5 * (Ax[j] + Ax[k]), 0.5 * (Ay[j] + Ay[k]), 0.5 * (Az[j] + Az[k])};
            if (RA[j] < RA[k]) {
                m[0] = Ax[j], m[1] = Ay[j], m[2] = Az[j];
            } else if (RA[k] < RA[j]) {
                m[0] = Ax[k], m[1] = Ay[k], m[2] = Az[k];
            }
            double mu = m[0] * u[0] + m[1] * u[1] + m[2] * u[2];
            double w[3] = {m[0] - mu * u[0], m[1] - mu * u[1], m[2] - mu * u[2]};
            d[e] = w[0] * O[(3 * e) * T + f] + w[1] * O[(3 * e + 1) * T + f] + w[2] * O[(3 * e + 2) * T + f];
            double w2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
            if (w2 < best) {
                best = w2;
                h = w[0] * Nx[f] + w[1] * Ny[f] + w[2] * Nz[f];
            }
        }
        D0[f] = d[0];
        D1[f] = d[1];
        D2[f] = d[2];
        H[f] = h;
        double habs = fabs(h), beta = 0.0;
        if (habs <= tol && d[0] >= -tol && d[1] >= -tol && d[2] >= -tol) {
            /* on the face: principal value, no solid angle. (On its plane off the face, the solid
             * angle is computed below: near an edge it is of order 1 even where h <= tol.) */
            OM[f] = 0.0;
            if (on_face < 0 || two_area[f] > two_area[on_face]) { /* the largest face: best conditioned */
                on_face = f;
                double sum = 0.0;
                for (int i = 0; i < 3; ++i) {
                    double al = d[i] * g->ell[3 * f + i] / two_area[f];
                    on_alpha[i] = al > 0 ? al : 0.0;
                    sum += on_alpha[i];
                }
                for (int i = 0; i < 3; ++i) on_alpha[i] /= sum;
            }
            continue;
        }
        for (int e = 0; e < 3; ++e) { /* edge-sum solid angle: does not cancel near the plane */
            int j = c3[(e + 1) % 3], k = c3[(e + 2) % 3];
            const double *u = ed + 3 * e;
            double l_j = Ax[j] * u[0] + Ay[j] * u[1] + Az[j] * u[2];
            double l_k = Ax[k] * u[0] + Ay[k] * u[1] + Az[k] * u[2], R0sq = d[e] * d[e] + h * h;
            beta += edge_angle(d[e], l_j, l_k, RA[j], RA[k], R0sq, habs);
        }
        OM[f] = h >= 0 ? beta : -beta;
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
    return on_face;
}

void tc_gc3d(const double *Pv, long V, const int *tri, long T, const int *edges, long E, const double *eu,
             const int *fe, const double *nrm, const double *two_area, const double *ell, const double *edir,
             const double *eout, const double *gbary, const double *X, long n, double tol, int nthreads, double *PHI,
             double *PSI, int *ONF, double *AL) {
    gc_tables g = {Pv, V, tri, T, edges, E, eu, fe, nrm, two_area, ell, edir, eout, gbary, NULL};
    tc_gc_prepare(&g);
#pragma omp parallel num_threads(nthreads)
    {
        double *buf = (double *)malloc(sizeof(double) * (tc_gc_workspace(&g) + 4 * (size_t)T));
        double *P = buf + tc_gc_workspace(&g), *OM = P + 3 * T;
#pragma omp for schedule(dynamic, 16)
        for (long p = 0; p < n; ++p) {
            double *phi = PHI + p * V, *psi = PSI + p * T, on_alpha[3];
            long on_face = tc_gc_point(&g, X + 3 * p, tol, buf, psi, P, OM, on_alpha);
            memset(phi, 0, sizeof(double) * (size_t)V);
            double omega_sum = 0.0;
            for (long f = 0; f < T; ++f) {
                phi[tri[f]] += P[f];
                phi[tri[T + f]] += P[T + f];
                phi[tri[2 * T + f]] += P[2 * T + f];
                omega_sum += OM[f];
            }
            if (ONF) {
                ONF[p] = (int)on_face;
                for (int i = 0; i < 3; ++i) AL[3 * p + i] = on_alpha[i];
            } else if (on_face >= 0) { /* the limit from inside: hat values with the jump weight */
                double jump = 1.0 - omega_sum / FOUR_PI;
                for (int i = 0; i < 3; ++i) phi[tri[i * T + on_face]] += jump * on_alpha[i];
            }
        }
        free(buf);
    }
    tc_gc_free(&g);
}
