/*
 * Native CPU kernel of torchcage's 3D mean value weights (float64).
 *
 * The same formulas as torchcage/families/mean_value/kernel3d.py (see its module docstring): the direct
 * vector form away from a face's support plane, the stable split form near it, and the
 * interpolating values for points on the cage. Blocks of TC_MVC_LANES points at a time (mvc3d_block_body),
 * one point at a time where a point needs it (mvc3d_point); OpenMP over blocks.
 * The tests check this kernel against the torch kernel and an mpmath reference.
 */
#define _GNU_SOURCE
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

/* Faces seen from more than this many times their longest edge always take the far-field rule. */
#define FAR_ALWAYS_RATIO 1e3

#define TWO_PI 6.283185307179586476925286766559

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector atan (libmvec, max error 4 ulp) in the edge loop. */
__attribute__((simd("notinbranch"))) double atan(double);
#endif

/* Stable split form of one face's weights (see _stable_face_weights in families/mean_value/kernel3d.py). The angle
 * theta = theta0 + delta is rebuilt here from the planar angle theta0 and the small delta rather
 * than taken from the edge pass: the terms delta / h^2 and theta * eps / h^2 cancel where x nears
 * an edge's line, and only a theta consistent with delta keeps that cancellation exact. The six
 * angles (delta and theta0 of each edge) are atans of quotients, taken in one vector loop of fixed
 * length (in the AVX2 build, libmvec's four-lane form twice; within a build the bits depend on the
 * arguments alone; the scalar atans took 5% of a mean value call on the Beast model): theta0 =
 * atan2(|s|, qq) is atan(|s| / qq) for qq > 0, else pi / 2 - atan(qq / |s|); delta = atan(h^2 X /
 * Y) for Y > 0, else atan2(h^2 X, Y) (rare, scalar). */
void tc_stable_face(double h, const double *s, const double *dots, const double *R, const double *ell,
                    const double *gram, double two_area, double *w) {
    double h2 = h * h, wind_angle = 0.0, S_rest = 0.0, tN[3];
    double N[3], safe_Nps[3], X[3], Y[3], s_abs[3], qq[3], q[8], at[8];
    for (int e = 0; e < 3; ++e) {
        s_abs[e] = fabs(s[e]);
        qq[e] = dots[e] - h2;
        N[e] = sqrt(s[e] * s[e] + h2 * ell[e] * ell[e]);
        double Nps = N[e] + s_abs[e];
        safe_Nps[e] = Nps > 0 ? Nps : 1.0;
        X[e] = qq[e] * ell[e] * ell[e] / safe_Nps[e] - s_abs[e];
        Y[e] = dots[e] * qq[e] + N[e] * s_abs[e];
        q[2 * e] = Y[e] > 0 ? h2 * X[e] / Y[e] : 0.0;
        q[2 * e + 1] = qq[e] > 0 ? s_abs[e] / qq[e] : (s_abs[e] > 0 ? qq[e] / s_abs[e] : 0.0);
    }
    q[6] = q[7] = 0.0;
#pragma omp simd
    for (int i = 0; i < 8; ++i) at[i] = atan(q[i]);
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        double sigma = s[e] >= 0 ? 1.0 : -1.0;
        double delta = Y[e] > 0 ? at[2 * e] : atan2(h2 * X[e], Y[e]);
        double delta_h2 = h2 > 0 ? delta / h2 : X[e] / Y[e];
        double theta0 = qq[e] > 0 ? at[2 * e + 1]
                                  : (s_abs[e] > 0 ? M_PI / 2 - at[2 * e + 1] : (qq[e] < 0 ? M_PI : 0.0));
        double theta = theta0 + delta;
        wind_angle += sigma * theta0;
        double safe_N = N[e] > 0 ? N[e] : 1.0;
        tN[e] = N[e] > 0 ? theta / safe_N : 1.0 / (R[j] * R[k]);
        double eps_h2 = ell[e] * ell[e] / (safe_N * safe_Nps[e]);
        S_rest += sigma * (delta_h2 - theta * eps_h2);
    }
    double wind = nearbyint(wind_angle / TWO_PI);
    double inv4A = 1.0 / (2.0 * two_area);
    for (int i = 0; i < 3; ++i) {
        double B = s[i] * S_rest + tN[0] * gram[3 * i] + tN[1] * gram[3 * i + 1] + tN[2] * gram[3 * i + 2];
        double wi = h * B * inv4A;
        if (wind != 0) wi += s[i] * TWO_PI * wind / (h != 0 ? h : 1.0) * inv4A;
        else if (h == 0) wi = 0.0;
        w[i] = wi;
    }
}

/*
 * inc_ptr (V + 1) and inc_idx (3T) list, for each vertex, its face corners as indices c * T + f
 * (CSR). Indices are int32. Layouts are structure-of-arrays so that the passes over vertices, edges and faces vectorise:
 * P: (3, V) vertices; tri: (3, T) corners; edges: (2, E) unique edges; fe: (3, T) index of the
 * edge opposite each corner, stored as (t[i+1], t[i+2]) when fs = +1 and reversed when -1;
 * nrm: (3, T) unit normals; two_area: (T,); ell: (T, 3) length of the edge opposite each corner;
 * gram: (T, 3, 3) E_i . E_e; far_bary (Q, 3) and far_qw (Q,): the far-field rule on the unit triangle
 * (node q of face f at sum_i far_bary[q, i] p_i, weight 2A far_qw[q] far_bary[q, i] for corner i), used
 * for points whose face weights sum in absolute value to more than cancel_c times their total, on
 * faces whose longest edge (longest: (T,)) is below far_c times the distance.
 * Batches (tc_mvc3d): B cages with one topology; the topology tables (tri, edges, fe, inc_ptr,
 * inc_idx, fs) and the far-field rule are shared, the geometric ones (P, nrm, two_area, ell, gram,
 * longest) and the on-cage tolerance tol carry a leading batch axis (B, ...).
 * X: (XB, n, 3) points, XB = 1 (one point set shared by every cage) or B.
 * Output W: (B, n, V) coordinates, normalised when normalize != 0, else the raw weights (on[b, p] = 1
 * marks points on the cage, whose rows hold their interpolating values either way; with normalize,
 * on[b, p] = 2 marks rows that are not finite: the total weight vanishes there, outside the cage).
 * A workspace that could not be allocated sets every flag to 3 and every row to NaN.
 */

/* One cage's tables (the batch element's slices of tc_mvc3d's arguments) and what is derived from
 * them once: the far-field centre and radius, and the thin faces. */
typedef struct {
    const double *P, *nrm, *two_area, *ell, *gram, *far_bary, *far_qw, *longest;
    double tol, centre[3], far2;
    const long *thin;
    long nthin;
} mvc3d_cage;

/* Per-thread scratch: vertex (4V), edge (8E) and face (5T) arrays. */
typedef struct {
    double *Ax, *Ay, *Az, *RA, *Nx, *Ny, *Nz, *Nn, *D, *Gx, *Gy, *Gz, *W0, *W1, *W2, *H, *RM;
} mvc3d_scratch;

/* The views of cage g and the topology tables (tri (3, T), edges (2, E), fe (3, T), fs (3, T))
 * that mvc3d_point and the block read. */
#define MVC3D_CAGE_VIEWS(g)                                                                                     \
    const double *P = (g)->P, *two_area = (g)->two_area, *ell = (g)->ell, *gram = (g)->gram,                     \
                 *longest = (g)->longest;                                                                        \
    const double tol = (g)->tol;                                                                                 \
    const int *t0 = tri, *t1 = tri + T, *t2 = tri + 2 * T;                                                       \
    const int *e0 = edges, *e1 = edges + E;                                                                      \
    const int *f0 = fe, *f1 = fe + T, *f2 = fe + 2 * T;                                                          \
    const double *s0 = fs, *s1 = fs + T, *s2 = fs + 2 * T;                                                       \
    const double *nx = (g)->nrm, *ny = (g)->nrm + T, *nz = (g)->nrm + 2 * T

/* The coordinates (raw weights unless normalize) of the point x0, x1, x2 against cage g, written to
 * w (V,); returns 1 when the point is on the cage (w holds the interpolating values), 2 when the
 * normalised coordinates are undefined (their sum is not finite: the total weight vanishes), else 0. */
static inline int mvc3d_point(const mvc3d_cage *g, long V, const int *tri, long T, const int *edges, long E,
                              const int *fe, const int *inc_ptr, const int *inc_idx, const double *fs, long Q,
                              double far_c, double cancel_c, double near_c, double x0, double x1, double x2,
                              int normalize, const mvc3d_scratch *sc, double *w) {
    MVC3D_CAGE_VIEWS(g);
    const double *far_bary = g->far_bary, *far_qw = g->far_qw;
    double *Ax = sc->Ax, *Ay = sc->Ay, *Az = sc->Az, *RA = sc->RA, *Nx = sc->Nx, *Ny = sc->Ny, *Nz = sc->Nz,
           *Nn = sc->Nn, *D = sc->D, *Gx = sc->Gx, *Gy = sc->Gy, *Gz = sc->Gz, *W0 = sc->W0, *W1 = sc->W1,
           *W2 = sc->W2, *H = sc->H, *RM = sc->RM;
#pragma omp simd
    for (long v = 0; v < V; ++v) {
        double ax = P[v] - x0, ay = P[V + v] - x1, az = P[2 * V + v] - x2;
        Ax[v] = ax;
        Ay[v] = ay;
        Az[v] = az;
        RA[v] = sqrt(ax * ax + ay * ay + az * az);
        w[v] = 0.0;
    }
    /* Edges: N = a_j x a_k, |N|, a_j . a_k, and the half-angle tangent argument. */
#pragma omp simd
    for (long q = 0; q < E; ++q) {
        int j = e0[q], k = e1[q];
        double ajx = Ax[j], ajy = Ay[j], ajz = Az[j], akx = Ax[k], aky = Ay[k], akz = Az[k];
        double cx = ajy * akz - ajz * aky, cy = ajz * akx - ajx * akz, cz = ajx * aky - ajy * akx;
        double nn = sqrt(cx * cx + cy * cy + cz * cz), d = ajx * akx + ajy * aky + ajz * akz;
        double rr = RA[j] * RA[k];
        Nx[q] = cx;
        Ny[q] = cy;
        Nz[q] = cz;
        Nn[q] = nn;
        D[q] = d;
        Gx[q] = nn / (rr + fabs(d)); /* tan of the half angle, or of its complement */
    }
#pragma omp simd
    for (long q = 0; q < E; ++q) Gx[q] = atan(Gx[q]);
    /* g N with g = theta / (2 |N|), theta = 2 atan(.) or pi - 2 atan(.). */
#pragma omp simd
    for (long q = 0; q < E; ++q) {
        double obtuse = D[q] < 0 ? 1.0 : 0.0; /* branch-free, so that the loop vectorises */
        double th = obtuse * M_PI + (1.0 - 2.0 * obtuse) * 2.0 * Gx[q];
        double gq = 0.5 * th / (Nn[q] > 1e-300 ? Nn[q] : 1e-300); /* any finite g will do where N = 0 */
        Gx[q] = gq * Nx[q];
        Gy[q] = gq * Ny[q];
        Gz[q] = gq * Nz[q];
    }
    /* Faces, direct vector form for all; pairs near a support plane are redone below. */
#pragma omp simd
    for (long f = 0; f < T; ++f) {
        int a = f0[f], b = f1[f], c = f2[f], i0 = t0[f];
        double sa = s0[f], sb = s1[f], sc_ = s2[f];
        double h = nx[f] * Ax[i0] + ny[f] * Ay[i0] + nz[f] * Az[i0];
        double mx = sa * Gx[a] + sb * Gx[b] + sc_ * Gx[c];
        double my = sa * Gy[a] + sb * Gy[b] + sc_ * Gy[c];
        double mz = sa * Gz[a] + sb * Gz[b] + sc_ * Gz[c];
        double inv = 1.0 / (two_area[f] * h);
        W0[f] = sa * (Nx[a] * mx + Ny[a] * my + Nz[a] * mz) * inv;
        W1[f] = sb * (Nx[b] * mx + Ny[b] * my + Nz[b] * mz) * inv;
        W2[f] = sc_ * (Nx[c] * mx + Ny[c] * my + Nz[c] * mz) * inv;
        H[f] = h;
        double r0 = RA[i0], r1 = RA[t1[f]], r2 = RA[t2[f]]; /* no fmin: it blocks vectorisation */
        double r01 = r0 < r1 ? r0 : r1;
        RM[f] = r01 < r2 ? r01 : r2;
    }
    long best = -1; /* the largest face holding the point (its barycentric values are the best conditioned) */
    double best_bc[3] = {0, 0, 0};
    for (long f = 0; f < T; ++f) {
        double h = H[f], rmin = RM[f];
        if (!(fabs(h) >= near_c * rmin && rmin > tol)) {
            const int t[3] = {t0[f], t1[f], t2[f]};
            const int fq[3] = {f0[f], f1[f], f2[f]};
            const double sg[3] = {s0[f], s1[f], s2[f]};
            double R[3] = {RA[t[0]], RA[t[1]], RA[t[2]]}, s[3], dots[3];
            for (int e = 0; e < 3; ++e) {
                int q = fq[e];
                s[e] = sg[e] * (Nx[q] * nx[f] + Ny[q] * ny[f] + Nz[q] * nz[f]);
                dots[e] = D[q];
            }
            const double *lf = ell + 3 * f;
            if ((fabs(h) <= tol && s[0] >= -tol * lf[0] && s[1] >= -tol * lf[1] && s[2] >= -tol * lf[2]) ||
                rmin <= tol) {
                /* On the face (or a vertex): barycentric (Lagrange) values, nothing else counts. */
                double bc[3];
                for (int i = 0; i < 3; ++i) bc[i] = rmin <= tol ? (R[i] <= tol ? 1.0 : 0.0) : (s[i] > 0 ? s[i] : 0.0);
                if (rmin <= tol || best < 0 || two_area[f] > two_area[best]) {
                    best = f;
                    for (int i = 0; i < 3; ++i) best_bc[i] = bc[i];
                }
                if (rmin <= tol) break; /* a vertex: its Lagrange values whichever face */
                continue;
            }
            double wf[3];
            tc_stable_face(h, s, dots, R, lf, gram + 9 * f, two_area[f], wf);
            W0[f] = wf[0];
            W1[f] = wf[1];
            W2[f] = wf[2];
        }
    }
    if (best >= 0) {
        double sum = best_bc[0] + best_bc[1] + best_bc[2];
        memset(w, 0, sizeof(double) * (size_t)V);
        w[t0[best]] += best_bc[0] / sum;
        w[t1[best]] += best_bc[1] / sum;
        w[t2[best]] += best_bc[2] / sum;
        return 1;
    }
    for (long q = 0; q < g->nthin; ++q) { /* thin faces seen from a few widths: the swept form */
        long f = g->thin[q];
        const int t[3] = {t0[f], t1[f], t2[f]};
        double a[3][3], wf[3], gf[3][3], Hf[3][6];
        for (int i = 0; i < 3; ++i) a[i][0] = Ax[t[i]], a[i][1] = Ay[t[i]], a[i][2] = Az[t[i]];
        if (!tc_thin_face((const double(*)[3])a, two_area[f])) continue;
        const double nf[3] = {nx[f], ny[f], nz[f]};
        tc_thin_mvc((const double(*)[3])a, nf, H[f], two_area[f], wf, gf, Hf);
        W0[f] = wf[0];
        W1[f] = wf[1];
        W2[f] = wf[2];
    }
    /* Gather the face-corner weights (W0, W1, W2 are contiguous) into the vertices. */
    double total = 0.0, abs_sum = 0.0;
    for (long v = 0; v < V; ++v) {
        double acc = 0.0;
        for (int k = inc_ptr[v]; k < inc_ptr[v + 1]; ++k) acc += W0[inc_idx[k]];
        w[v] = acc;
        total += acc;
    }
    int seen_tiny = 0; /* some face seen below 1e-3 of its distance: its vector form cancels */
#pragma omp simd reduction(+ : abs_sum) reduction(| : seen_tiny)
    for (long f = 0; f < T; ++f) {
        abs_sum += fabs(W0[f] + W1[f] + W2[f]);
        seen_tiny |= longest[f] * FAR_ALWAYS_RATIO < RM[f];
    }
    if (abs_sum > cancel_c * fabs(total) || seen_tiny) {
        /* The face weights cancel (far outside), or faces are seen so small that the vector
         * form's error eps (r / edge)^3 would hide the cancellation: redo faces seen small
         * by quadrature, w_i = h * sum_q c_qi / |p_q - x|^4, and gather again. */
        for (long f = 0; f < T; ++f) {
            if (!(longest[f] < far_c * RM[f])) continue;
            /* the nodes from the corners (no (T, Q, 3) tables to build for every cage and call) */
            const int i0 = t0[f], i1 = t1[f], i2 = t2[f];
            const double p00 = P[i0], p01 = P[V + i0], p02 = P[2 * V + i0], p10 = P[i1], p11 = P[V + i1];
            const double p12 = P[2 * V + i1], p20 = P[i2], p21 = P[V + i2], p22 = P[2 * V + i2], A2 = two_area[f];
            double acc0 = 0.0, acc1 = 0.0, acc2 = 0.0;
#pragma omp simd reduction(+ : acc0, acc1, acc2)
            for (long k = 0; k < Q; ++k) {
                const double b0 = far_bary[3 * k], b1 = far_bary[3 * k + 1], b2 = far_bary[3 * k + 2];
                double d0 = b0 * p00 + b1 * p10 + b2 * p20 - x0, d1 = b0 * p01 + b1 * p11 + b2 * p21 - x1;
                double d2 = b0 * p02 + b1 * p12 + b2 * p22 - x2;
                double r2 = d0 * d0 + d1 * d1 + d2 * d2, inv = 1.0 / (r2 * r2), c = A2 * far_qw[k];
                acc0 += c * b0 * inv;
                acc1 += c * b1 * inv;
                acc2 += c * b2 * inv;
            }
            double h = H[f];
            W0[f] = h * acc0;
            W1[f] = h * acc1;
            W2[f] = h * acc2;
        }
        for (long v = 0; v < V; ++v) {
            double acc = 0.0;
            for (int k = inc_ptr[v]; k < inc_ptr[v + 1]; ++k) acc += W0[inc_idx[k]];
            w[v] = acc;
        }
    }
    if (!normalize) return 0;
    const double xp[3] = {x0, x1, x2};
    double inv = 1.0 / tc_mv_total(w, V, P, 1, V, 3, xp, g->centre, g->far2), sum = 0.0;
#pragma omp simd reduction(+ : sum)
    for (long v = 0; v < V; ++v) {
        w[v] *= inv;
        sum += w[v]; /* (only its finiteness is read: any order will do) */
    }
    return isfinite(sum) ? 0 : 2;
}

/*
 * Blocks of TC_MVC_LANES points at once: every per-vertex, per-edge and per-face quantity is stored
 * [index][lane], so that each inner loop runs over the lanes with contiguous loads (one SIMD
 * operation, or two, per step) and the index tables are read once per block rather than once per
 * point. The formulas and their order of evaluation are mvc3d_point's, so that a point's values do
 * not depend on the path that computed them beyond the last bits of libmvec's atan (which the
 * per-point path's vector loops also call, but its scalar remainder does not). Pairs near a support
 * plane take tc_stable_face and thin faces tc_thin_mvc lane by lane, as in mvc3d_point; a lane whose
 * point is on the cage, or whose weights cancel (the far-field rule), is redone by mvc3d_point.
 */
#ifndef TC_MVC_LANES
#define TC_MVC_LANES 8
#endif
#define LN TC_MVC_LANES

/* Per-thread scratch of a block: vertex (5V: A, |A|, the gathered weights), edge (5E: N, g, and |N|
 * while g is made) and face (3T: the corner weights) arrays of LN lanes each, and the list of faces
 * that some lane sees near their support plane. The face pass reads N and g alone (not the three
 * products g N, nor h and the nearest corner's distance, which the rare careful forms recompute): a
 * smaller working set, measured faster. */
typedef struct {
    double *Ax, *Ay, *Az, *RA, *acc, *Nx, *Ny, *Nz, *G, *NN, *Wc;
    long *near;
} mvc3d_block_scratch;

static size_t mvc3d_block_doubles(long V, long E, long T) {
    return (size_t)LN * (5 * (size_t)V + 5 * (size_t)E + 3 * (size_t)T);
}

static void mvc3d_block_carve(double *buf, long V, long E, long T, mvc3d_block_scratch *bs) {
    bs->Ax = buf, bs->Ay = bs->Ax + LN * V, bs->Az = bs->Ay + LN * V, bs->RA = bs->Az + LN * V;
    bs->acc = bs->RA + LN * V;
    bs->Nx = bs->acc + LN * V, bs->Ny = bs->Nx + LN * E, bs->Nz = bs->Ny + LN * E;
    bs->G = bs->Nz + LN * E, bs->NN = bs->G + LN * E, bs->Wc = bs->NN + LN * E;
}

#if defined(__GNUC__)
#define TC_ALWAYS_INLINE inline __attribute__((always_inline))
#else
#define TC_ALWAYS_INLINE inline
#endif
#define MVC3D_BLOCK_PARAMS                                                                                          \
    const mvc3d_cage *g, long V, const int *tri, long T, const int *edges, long E, const int *fe, const int *inc_ptr, \
        const int *inc_idx, const double *fs, long Q, double far_c, double cancel_c, double near_c, const double *X, \
        int normalize, const mvc3d_scratch *sc, const mvc3d_block_scratch *bs, double *w, unsigned char *on
#define MVC3D_BLOCK_ARGS \
    g, V, tri, T, edges, E, fe, inc_ptr, inc_idx, fs, Q, far_c, cancel_c, near_c, X, normalize, sc, bs, w, on

/* The rows w[l * V + v] = acc[LN * v + l] * inv[l] (the lanes' values, [vertex][lane], written as
 * rows, scaled), and sum[l] += each row's values (only their finiteness is read: any order will do).
 * Four vertices and four lanes at a time by a 4 x 4 transpose in vector registers where the compiler
 * has __builtin_shufflevector (gcc 12, clang) and LN is 8; else one value at a time. acc is
 * 64-byte aligned; w need not be. */
#if LN == 8 && (defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 12))
typedef double tc_v4d __attribute__((vector_size(32)));                        /* (32-byte aligned) */
typedef double tc_v4du __attribute__((vector_size(32), aligned(8), may_alias)); /* (any double's address) */
#define MVC3D_SHUFFLE_ROWS 1
#endif
static TC_ALWAYS_INLINE void mvc3d_rows_out(const double *acc, const double *inv, long V, double *w, double *sum) {
    long v0 = 0;
#ifdef MVC3D_SHUFFLE_ROWS
    tc_v4d s4[LN];
    for (int l = 0; l < LN; ++l) s4[l] = (tc_v4d){0.0, 0.0, 0.0, 0.0};
    for (; v0 + 4 <= V; v0 += 4) {
        const tc_v4d *a = (const tc_v4d *)(acc + LN * v0); /* a[2 k + h]: vertex v0 + k, lanes 4 h .. 4 h + 3 */
        for (int h = 0; h < 2; ++h) {
            const tc_v4d t0 = __builtin_shufflevector(a[h], a[2 + h], 0, 4, 2, 6);
            const tc_v4d t1 = __builtin_shufflevector(a[h], a[2 + h], 1, 5, 3, 7);
            const tc_v4d t2 = __builtin_shufflevector(a[4 + h], a[6 + h], 0, 4, 2, 6);
            const tc_v4d t3 = __builtin_shufflevector(a[4 + h], a[6 + h], 1, 5, 3, 7);
            const int l = 4 * h;
            const tc_v4d o0 = __builtin_shufflevector(t0, t2, 0, 1, 4, 5) * inv[l];
            const tc_v4d o1 = __builtin_shufflevector(t1, t3, 0, 1, 4, 5) * inv[l + 1];
            const tc_v4d o2 = __builtin_shufflevector(t0, t2, 2, 3, 6, 7) * inv[l + 2];
            const tc_v4d o3 = __builtin_shufflevector(t1, t3, 2, 3, 6, 7) * inv[l + 3];
            *(tc_v4du *)(w + V * l + v0) = o0, *(tc_v4du *)(w + V * (l + 1) + v0) = o1;
            *(tc_v4du *)(w + V * (l + 2) + v0) = o2, *(tc_v4du *)(w + V * (l + 3) + v0) = o3;
            s4[l] += o0, s4[l + 1] += o1, s4[l + 2] += o2, s4[l + 3] += o3;
        }
    }
    for (int l = 0; l < LN; ++l) sum[l] += (s4[l][0] + s4[l][1]) + (s4[l][2] + s4[l][3]);
#endif
    for (long v = v0; v < V; ++v) {
        const double *av = acc + LN * v;
        for (int l = 0; l < LN; ++l) {
            const double wv = av[l] * inv[l];
            w[V * l + v] = wv;
            sum[l] += wv;
        }
    }
}

/* The coordinates of the LN points X[0 .. LN) (rows of 3) against cage g, into the rows w[l * V ..)
 * with their flags on[l] (as mvc3d_point's return value). Compiled twice below: for the library's
 * target and, where the compiler and libmvec allow, for AVX-512 (chosen at run time). */
static TC_ALWAYS_INLINE void mvc3d_block_body(MVC3D_BLOCK_PARAMS) {
    MVC3D_CAGE_VIEWS(g);
    double *Ax = bs->Ax, *Ay = bs->Ay, *Az = bs->Az, *RA = bs->RA, *acc = bs->acc, *Nx = bs->Nx, *Ny = bs->Ny,
           *Nz = bs->Nz, *G = bs->G, *NN = bs->NN, *Wc = bs->Wc;
    long *near = bs->near;
    double x0[LN], x1[LN], x2[LN], total[LN], abs_sum[LN];
    unsigned long long tiny[LN];
    int redo[LN]; /* redo: the lane is left to mvc3d_point (on the cage, or the far-field rule) */
    for (int l = 0; l < LN; ++l) {
        x0[l] = X[3 * l], x1[l] = X[3 * l + 1], x2[l] = X[3 * l + 2];
        tiny[l] = 0, redo[l] = 0;
    }
    for (long v = 0; v < V; ++v) {
        const double p0 = P[v], p1 = P[V + v], p2 = P[2 * V + v];
        double *ax = Ax + LN * v, *ay = Ay + LN * v, *az = Az + LN * v, *ra = RA + LN * v;
#pragma omp simd
        for (int l = 0; l < LN; ++l) {
            double a0 = p0 - x0[l], a1 = p1 - x1[l], a2 = p2 - x2[l];
            ax[l] = a0, ay[l] = a1, az[l] = a2;
            ra[l] = sqrt(a0 * a0 + a1 * a1 + a2 * a2);
        }
    }
    /* Edges: N = a_j x a_k, |N|, and the half-angle tangent argument with the sign of a_j . a_k;
     * then its atan and g = theta / (2 |N|) (mvc3d_point's edge loops, the last two over all lanes
     * at once). */
    for (long q = 0; q < E; ++q) {
        const long j = LN * (long)e0[q], k = LN * (long)e1[q];
        double *nxq = Nx + LN * q, *nyq = Ny + LN * q, *nzq = Nz + LN * q, *gq = G + LN * q, *nnq = NN + LN * q;
#pragma omp simd
        for (int l = 0; l < LN; ++l) {
            double ajx = Ax[j + l], ajy = Ay[j + l], ajz = Az[j + l], akx = Ax[k + l], aky = Ay[k + l],
                   akz = Az[k + l];
            double cx = ajy * akz - ajz * aky, cy = ajz * akx - ajx * akz, cz = ajx * aky - ajy * akx;
            double nn = sqrt(cx * cx + cy * cy + cz * cz), d = ajx * akx + ajy * aky + ajz * akz;
            double rr = RA[j + l] * RA[k + l];
            nxq[l] = cx, nyq[l] = cy, nzq[l] = cz;
            const double t = nn / (rr + fabs(d));
            gq[l] = d < 0 ? -t : t; /* (an obtuse angle: a negative argument, -0 included) */
            nnq[l] = nn;
        }
    }
#pragma omp simd
    for (long i = 0; i < LN * E; ++i) G[i] = atan(G[i]);
#pragma omp simd
    for (long i = 0; i < LN * E; ++i) { /* theta = 2 atan(t), or pi - 2 atan(|t|) where obtuse */
        const double at = G[i], nn = NN[i];
        const double th = 2.0 * at + (copysign(1.0, at) < 0 ? M_PI : 0.0); /* (-0 too; signbit does not vectorise) */
        G[i] = 0.5 * th / (nn > 1e-300 ? nn : 1e-300);
    }
    /* Faces, direct vector form; the faces that some lane sees near their support plane are listed
     * (a bit per face and lane, 64 faces at a time, so that the lane loop needs no reduction). */
    long nnear = 0;
    for (long fc = 0; fc < T; fc += 64) {
        const long fend = fc + 64 < T ? fc + 64 : T;
        unsigned long long bits[LN];
        for (int l = 0; l < LN; ++l) bits[l] = 0;
        for (long f = fc; f < fend; ++f) {
            const long a = LN * (long)f0[f], b = LN * (long)f1[f], c = LN * (long)f2[f], i0 = LN * (long)t0[f],
                       i1 = LN * (long)t1[f], i2 = LN * (long)t2[f];
            const double sa = s0[f], sb = s1[f], sc_ = s2[f], nxf = nx[f], nyf = ny[f], nzf = nz[f];
            const double area = two_area[f], far_always = longest[f] * FAR_ALWAYS_RATIO;
            const int shift = (int)(f - fc);
            double *w0 = Wc + LN * f, *w1 = Wc + LN * (T + f), *w2 = Wc + LN * (2 * T + f);
#pragma omp simd
            for (int l = 0; l < LN; ++l) {
                double h = nxf * Ax[i0 + l] + nyf * Ay[i0 + l] + nzf * Az[i0 + l];
                const double ga = G[a + l], gb = G[b + l], gc = G[c + l];
                const double nax = Nx[a + l], nay = Ny[a + l], naz = Nz[a + l], nbx = Nx[b + l], nby = Ny[b + l],
                             nbz = Nz[b + l], ncx = Nx[c + l], ncy = Ny[c + l], ncz = Nz[c + l];
                double mx = sa * (ga * nax) + sb * (gb * nbx) + sc_ * (gc * ncx);
                double my = sa * (ga * nay) + sb * (gb * nby) + sc_ * (gc * ncy);
                double mz = sa * (ga * naz) + sb * (gb * nbz) + sc_ * (gc * ncz);
                double inv = 1.0 / (area * h);
                w0[l] = sa * (nax * mx + nay * my + naz * mz) * inv;
                w1[l] = sb * (nbx * mx + nby * my + nbz * mz) * inv;
                w2[l] = sc_ * (ncx * mx + ncy * my + ncz * mz) * inv;
                double r0 = RA[i0 + l], r1 = RA[i1 + l], r2 = RA[i2 + l];
                double r01 = r0 < r1 ? r0 : r1;
                double rmin = r01 < r2 ? r01 : r2;
                unsigned long long near_bit = !(fabs(h) >= near_c * rmin && rmin > tol);
                bits[l] |= near_bit << shift;
                tiny[l] |= far_always < rmin ? 1ULL : 0ULL;
            }
        }
        unsigned long long any = 0;
        for (int l = 0; l < LN; ++l) any |= bits[l];
        for (; any; any &= any - 1) near[nnear++] = fc + tc_ctz64(any);
    }
    /* Pairs near a support plane: the stable split form, lane by lane; a lane on the cage is redone whole. */
    for (long i = 0; i < nnear; ++i) {
        const long f = near[i];
        const int t[3] = {t0[f], t1[f], t2[f]};
        const int fq[3] = {f0[f], f1[f], f2[f]};
        const double sg[3] = {s0[f], s1[f], s2[f]};
        const double *lf = ell + 3 * f;
        for (int l = 0; l < LN; ++l) {
            const long i0 = LN * (long)t[0] + l;
            /* h and rmin recomputed (as the face pass has them; at the threshold either form serves) */
            const double h = nx[f] * Ax[i0] + ny[f] * Ay[i0] + nz[f] * Az[i0];
            const double r0 = RA[i0], r1 = RA[LN * (long)t[1] + l], r2 = RA[LN * (long)t[2] + l];
            const double r01 = r0 < r1 ? r0 : r1, rmin = r01 < r2 ? r01 : r2;
            if (redo[l] || (fabs(h) >= near_c * rmin && rmin > tol)) continue;
            double R[3], s[3], dots[3], wf[3];
            for (int e = 0; e < 3; ++e) {
                const long q = LN * (long)fq[e] + l, j = LN * (long)e0[fq[e]] + l, k = LN * (long)e1[fq[e]] + l;
                R[e] = RA[LN * (long)t[e] + l];
                s[e] = sg[e] * (Nx[q] * nx[f] + Ny[q] * ny[f] + Nz[q] * nz[f]);
                dots[e] = Ax[j] * Ax[k] + Ay[j] * Ay[k] + Az[j] * Az[k];
            }
            if ((fabs(h) <= tol && s[0] >= -tol * lf[0] && s[1] >= -tol * lf[1] && s[2] >= -tol * lf[2]) ||
                rmin <= tol) {
                redo[l] = 1; /* on the cage: its interpolating values */
                continue;
            }
            tc_stable_face(h, s, dots, R, lf, gram + 9 * f, two_area[f], wf);
            Wc[LN * f + l] = wf[0];
            Wc[LN * (T + f) + l] = wf[1];
            Wc[LN * (2 * T + f) + l] = wf[2];
        }
    }
    for (long q = 0; q < g->nthin; ++q) { /* thin faces seen from a few widths: the swept form */
        const long f = g->thin[q];
        const int t[3] = {t0[f], t1[f], t2[f]};
        const double nf[3] = {nx[f], ny[f], nz[f]};
        for (int l = 0; l < LN; ++l) {
            if (redo[l]) continue;
            double a[3][3], wf[3], gf[3][3], Hf[3][6];
            for (int i = 0; i < 3; ++i) {
                const long v = LN * (long)t[i] + l;
                a[i][0] = Ax[v], a[i][1] = Ay[v], a[i][2] = Az[v];
            }
            if (!tc_thin_face((const double(*)[3])a, two_area[f])) continue;
            const double h = nf[0] * a[0][0] + nf[1] * a[0][1] + nf[2] * a[0][2];
            tc_thin_mvc((const double(*)[3])a, nf, h, two_area[f], wf, gf, Hf);
            Wc[LN * f + l] = wf[0];
            Wc[LN * (T + f) + l] = wf[1];
            Wc[LN * (2 * T + f) + l] = wf[2];
        }
    }
    /* Gather the face-corner weights into the vertices, corners in mvc3d_point's order. */
    for (int l = 0; l < LN; ++l) total[l] = 0.0, abs_sum[l] = 0.0;
    for (long v = 0; v < V; ++v) {
        double *av = acc + LN * v;
#pragma omp simd
        for (int l = 0; l < LN; ++l) av[l] = 0.0;
        for (int k = inc_ptr[v]; k < inc_ptr[v + 1]; ++k) {
            const double *wk = Wc + LN * (long)inc_idx[k];
#pragma omp simd
            for (int l = 0; l < LN; ++l) av[l] += wk[l];
        }
#pragma omp simd
        for (int l = 0; l < LN; ++l) total[l] += av[l];
    }
    for (long f = 0; f < T; ++f) {
        const double *w0 = Wc + LN * f, *w1 = Wc + LN * (T + f), *w2 = Wc + LN * (2 * T + f);
#pragma omp simd
        for (int l = 0; l < LN; ++l) abs_sum[l] += fabs(w0[l] + w1[l] + w2[l]);
    }
    /* Lanes left to mvc3d_point: on the cage, or weights that cancel (the far-field rule). The others
     * are normalised by tc_mv_total: the sum, total[l] (the same additions in the same order), or
     * far from the cage the first moment. */
    double inv[LN], sum[LN];
    for (int l = 0; l < LN; ++l) {
        redo[l] |= abs_sum[l] > cancel_c * fabs(total[l]) || tiny[l];
        inv[l] = 1.0, sum[l] = 0.0; /* (raw weights: times 1, exactly) */
        if (redo[l] || !normalize) continue;
        const double xp[3] = {x0[l], x1[l], x2[l]};
        double y2 = 0.0, norm = total[l];
        for (int k = 0; k < 3; ++k) y2 += (xp[k] - g->centre[k]) * (xp[k] - g->centre[k]);
        if (y2 > g->far2) {
            double *wl = w + V * l;
            for (long v = 0; v < V; ++v) wl[v] = acc[LN * v + l];
            norm = tc_mv_total(wl, V, P, 1, V, 3, xp, g->centre, g->far2);
        }
        inv[l] = 1.0 / norm;
    }
    mvc3d_rows_out(acc, inv, V, w, sum);
    for (int l = 0; l < LN; ++l) {
        if (!redo[l]) on[l] = normalize && !isfinite(sum[l]) ? 2 : 0;
        else
            on[l] = (unsigned char)mvc3d_point(g, V, tri, T, edges, E, fe, inc_ptr, inc_idx, fs, Q, far_c, cancel_c,
                                               near_c, x0[l], x1[l], x2[l], normalize, sc, w + V * l);
    }
}

static void mvc3d_block(MVC3D_BLOCK_PARAMS) { mvc3d_block_body(MVC3D_BLOCK_ARGS); }

/* The AVX-512 instance: one 512-bit operation per lane loop, libmvec's 8-lane atan (_ZGVeN8v_atan).
 * Only with gcc and glibc's vector math (TC_LIBMVEC) on x86-64; the CPU is asked at run time. */
#if defined(TC_LIBMVEC) && defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 8 && \
    !defined(TC_NO_AVX512)
#define MVC3D_AVX512 1
__attribute__((target("avx512f,avx512dq,avx512vl,avx2,fma,prefer-vector-width=512"))) static void mvc3d_block_avx512(
    MVC3D_BLOCK_PARAMS) {
    mvc3d_block_body(MVC3D_BLOCK_ARGS);
}
static int mvc3d_has_avx512(void) {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
           __builtin_cpu_supports("avx512vl");
}
#endif

/* A workspace not allocated: every row NaN, every flag 3 (the glue raises MemoryError). */
static void mvc3d_failed(long nw, long nflags, double *W, unsigned char *on) {
    for (long i = 0; i < nw; ++i) W[i] = NAN;
    memset(on, 3, (size_t)nflags);
}

void tc_mvc3d(long B, const double *P, long V, const int *tri, long T, const int *edges, long E, const int *fe,
              const int *inc_ptr, const int *inc_idx, const double *fs, const double *nrm, const double *two_area,
              const double *ell, const double *gram, const double *far_bary, const double *far_qw,
              const double *longest, long Q, double far_c, double cancel_c, const double *X, long XB, long n,
              const double *tol, double near_c, int nthreads, double *W, unsigned char *on, int normalize) {
    if (B <= 0 || n <= 0) return;
    if (XB != 1 && XB != B) { /* (the glue refuses this; never read past X: NaN, which callers report) */
        for (long i = 0; i < B * n * V; ++i) W[i] = NAN;
        memset(on, 0, (size_t)(B * n));
        return;
    }
    const long xs = XB == 1 ? 0 : 3 * n; /* one point set shared by every cage, or one per cage */
    mvc3d_cage *cages = (mvc3d_cage *)malloc(sizeof(mvc3d_cage) * (size_t)B);
    /* Thin faces (tc_thin_face) of each cage: their pairs seen from a few widths take the swept form. */
    long *thin = (long *)malloc(sizeof(long) * (size_t)(T > 0 ? T : 1) * (size_t)B);
    if (cages == NULL || thin == NULL) {
        free(cages);
        free(thin);
        mvc3d_failed(B * n * V, B * n, W, on);
        return;
    }
    for (long b = 0; b < B; ++b) {
        mvc3d_cage *g = cages + b;
        g->P = P + 3 * V * b;
        g->nrm = nrm + 3 * T * b;
        g->two_area = two_area + T * b;
        g->ell = ell + 3 * T * b;
        g->gram = gram + 9 * T * b;
        g->far_bary = far_bary;
        g->far_qw = far_qw;
        g->longest = longest + T * b;
        g->tol = tol[b];
        g->far2 = tc_far_centre(g->P, V, 1, V, 3, g->centre);
        long *tb = thin + T * b, nthin = 0;
        for (long f = 0; f < T; ++f)
            if (g->two_area[f] > 0 && g->longest[f] * g->longest[f] > TC_THIN_ASPECT * g->two_area[f]) tb[nthin++] = f;
        g->thin = tb;
        g->nthin = nthin;
    }
    /* Work items: each cage's full blocks of LN points, then its last n % LN points one by one. */
    const long nb = n / LN, per = nb + (n - nb * LN);
#ifdef MVC3D_AVX512
    const int avx512 = nb > 0 && mvc3d_has_avx512();
#endif
    int failed = 0; /* a thread could not allocate its scratch */
#pragma omp parallel num_threads(nthreads)
    {
        double *buf = (double *)malloc(sizeof(double) * (4 * (size_t)V + 8 * (size_t)E + 5 * (size_t)T));
        if (buf == NULL) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp barrier
        if (failed) { /* (every thread: none enters the worksharing loop) */
            free(buf);
            goto done;
        }
        mvc3d_scratch sc;
        sc.Ax = buf, sc.Ay = sc.Ax + V, sc.Az = sc.Ay + V, sc.RA = sc.Az + V;
        sc.Nx = sc.RA + V, sc.Ny = sc.Nx + E, sc.Nz = sc.Ny + E, sc.Nn = sc.Nz + E, sc.D = sc.Nn + E;
        sc.Gx = sc.D + E, sc.Gy = sc.Gx + E, sc.Gz = sc.Gy + E;
        sc.W0 = sc.Gz + E, sc.W1 = sc.W0 + T, sc.W2 = sc.W1 + T, sc.H = sc.W2 + T, sc.RM = sc.H + T;
        mvc3d_block_scratch bs = {0};
        void *bbuf = NULL; /* (aligned by hand to 64 bytes: the lane rows start cache lines) */
        long *near = (long *)malloc(sizeof(long) * (size_t)(T > 0 ? T : 1));
        if (nb > 0) bbuf = malloc(sizeof(double) * mvc3d_block_doubles(V, E, T) + 64);
        if (bbuf != NULL) mvc3d_block_carve((double *)(((size_t)bbuf + 63) & ~(size_t)63), V, E, T, &bs);
        bs.near = near;
#pragma omp for schedule(dynamic, 8)
        for (long i = 0; i < B * per; ++i) {
            const long b = i / per, k = i - b * per;
            const long p = k < nb ? LN * k : LN * nb + (k - nb), m = k < nb ? LN : 1;
            const double *x = X + xs * b + 3 * p;
            const long o = b * n + p;
            if (m == LN && bbuf != NULL && near != NULL) {
#ifdef MVC3D_AVX512
                if (avx512) {
                    mvc3d_block_avx512(cages + b, V, tri, T, edges, E, fe, inc_ptr, inc_idx, fs, Q, far_c, cancel_c,
                                       near_c, x, normalize, &sc, &bs, W + o * V, on + o);
                    continue;
                }
#endif
                mvc3d_block(cages + b, V, tri, T, edges, E, fe, inc_ptr, inc_idx, fs, Q, far_c, cancel_c, near_c, x,
                            normalize, &sc, &bs, W + o * V, on + o);
                continue;
            }
            for (long r = 0; r < m; ++r) /* (one point, or a block without its scratch) */
                on[o + r] = (unsigned char)mvc3d_point(cages + b, V, tri, T, edges, E, fe, inc_ptr, inc_idx, fs, Q,
                                                       far_c, cancel_c, near_c, x[3 * r], x[3 * r + 1], x[3 * r + 2],
                                                       normalize, &sc, W + (o + r) * V);
        }
        free(near);
        free(bbuf);
        free(buf);
    done:;
    }
    free(thin);
    free(cages);
    if (failed) mvc3d_failed(B * n * V, B * n, W, on);
}
