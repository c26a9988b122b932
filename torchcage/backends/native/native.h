/* Shared helpers of torchcage's native kernels (header-only, included by the .c files). */
#ifndef TORCHCAGE_NATIVE_H
#define TORCHCAGE_NATIVE_H

#include <math.h>
#include <stddef.h>

static inline void cross3(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static inline double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* The index of the lowest set bit of v != 0 (a compiler builtin where there is one). */
static inline int tc_ctz64(unsigned long long v) {
#if defined(__GNUC__) || defined(__clang__)
    return __builtin_ctzll(v);
#else
    int k = 0;
    for (; !(v & 1ULL); v >>= 1) ++k;
    return k;
#endif
}

/* Per-face scratch of the direct vector form of 3D mean value weights, as the VJP kernels store it
 * (mvc3d_vjp.c, mvc3d_vjp_near.c): a_i = p_i - x (9), N_e = a_{e+1} x a_{e+2} (9), |N_e| (3),
 * d_e = a_{e+1} . a_{e+2} (3), theta_e (3), g_e = theta_e / (2 |N_e|) (3), m = sum_e g_e N_e (3),
 * det = a_1 . N_1, and the corner weights w_i (3). */
enum { TC_FA_A = 0, TC_FA_N = 9, TC_FA_NN = 18, TC_FA_D = 21, TC_FA_TH = 24, TC_FA_G = 27, TC_FA_M = 30,
       TC_FA_DET = 33, TC_FA_W = 34, TC_FA_SIZE = 37 };

/* Fills one face's scratch s (layout above, all but the weights w) for the point x: t its corners
 * in P (V, 3); R (3) gets the corners' distances |a_i|. Returns the smallest of them. */
static inline double tc_mvc_face_direct(const double *P, const int *t, const double *x, double *s, double *R) {
    double *a = s + TC_FA_A, *N = s + TC_FA_N, *m = s + TC_FA_M, rmin = INFINITY;
    for (int i = 0; i < 3; ++i) {
        const double *pi = P + 3 * t[i];
        for (int k = 0; k < 3; ++k) a[3 * i + k] = pi[k] - x[k];
        R[i] = sqrt(dot3(a + 3 * i, a + 3 * i));
        rmin = fmin(rmin, R[i]);
    }
    m[0] = m[1] = m[2] = 0.0;
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        cross3(a + 3 * j, a + 3 * k, N + 3 * e);
        double nn = sqrt(dot3(N + 3 * e, N + 3 * e)), d = dot3(a + 3 * j, a + 3 * k);
        double th = atan2(nn, d), ge = th / (2.0 * (nn > 0 ? nn : 1.0));
        s[TC_FA_NN + e] = nn, s[TC_FA_D + e] = d, s[TC_FA_TH + e] = th, s[TC_FA_G + e] = ge;
        for (int c = 0; c < 3; ++c) m[c] += ge * N[3 * e + c];
    }
    s[TC_FA_DET] = dot3(a, N);
    return rmin;
}

/* Reverse mode of one face's direct-form weights (derivation: families/mean_value/vjp3d.py): with s
 * the face's scratch (layout above), t its corners and wbar (V,) the cotangent of the raw weights,
 * adds dL/dp_{t_i} to gp (V, 3) and dL/dx = -sum_i abar_i to gx (3). */
static inline void tc_mvc_face_adjoint(const double *s, const int *t, const double *wbar, double *gp, double *gx) {
    const double *a = s + TC_FA_A, *N = s + TC_FA_N, *m = s + TC_FA_M, *w = s + TC_FA_W;
    const double inv_det = 1.0 / s[TC_FA_DET];
    double wb[3], mbar[3] = {0, 0, 0}, Nbar[9], abar[9], det_bar = 0.0;
    for (int i = 0; i < 3; ++i) {
        wb[i] = wbar[t[i]] * inv_det;
        det_bar -= wb[i] * w[i];
        for (int c = 0; c < 3; ++c) {
            mbar[c] += wb[i] * N[3 * i + c];
            Nbar[3 * i + c] = wb[i] * m[c];
        }
    }
    for (int i = 0; i < 3; ++i)
        for (int c = 0; c < 3; ++c) abar[3 * i + c] = det_bar * N[3 * i + c];
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        double nn = s[TC_FA_NN + e], d = s[TC_FA_D + e], safe_nn = nn > 0 ? nn : 1.0;
        double gbar = dot3(N + 3 * e, mbar), th_bar = gbar / (2.0 * safe_nn);
        double r2 = nn * nn + d * d, safe_r2 = r2 > 0 ? r2 : 1.0;
        double n_bar = -gbar * s[TC_FA_TH + e] / (2.0 * safe_nn * safe_nn) + th_bar * d / safe_r2;
        double d_bar = -th_bar * nn / safe_r2, coef = n_bar / safe_nn, *Nb = Nbar + 3 * e, cj[3], ck[3];
        for (int c = 0; c < 3; ++c) Nb[c] += s[TC_FA_G + e] * mbar[c] + coef * N[3 * e + c];
        cross3(a + 3 * k, Nb, cj);
        cross3(Nb, a + 3 * j, ck);
        for (int c = 0; c < 3; ++c) {
            abar[3 * j + c] += d_bar * a[3 * k + c] + cj[c];
            abar[3 * k + c] += d_bar * a[3 * j + c] + ck[c];
        }
    }
    for (int i = 0; i < 3; ++i) {
        double *dst = gp + 3 * t[i];
        for (int c = 0; c < 3; ++c) {
            dst[c] += abar[3 * i + c];
            gx[c] -= abar[3 * i + c];
        }
    }
}

/* The argument of the log in int_e dl / r = log(arg) along an edge from p_j to p_k: l_j, l_k the
 * endpoints' positions along the edge's direction from the point's foot, R_j, R_k their distances,
 * c2 the squared distance from the point to the edge's line. Three forms, each free of cancellation
 * where it is used; all are computed, then one selected, so that loops over edges vectorise. */
static inline double tc_edge_log_arg(double l_j, double l_k, double R_j, double R_k, double c2) {
    double pk = R_k + l_k, mj = R_j - l_j, pj = R_j + l_j, mk = R_k - l_k, both = pk * mj;
    double num = l_j >= 0 ? pk : (l_k <= 0 ? mj : both);
    double den = l_j >= 0 ? pj : (l_k <= 0 ? mk : c2);
    /* On the edge (num = 0 at an end, den = 0 inside it) I is infinite and every use multiplies it
     * by 0: keep the log finite (log(1) = 0 for num = 0; at most log(1e300)) so that the product is
     * 0 and not NaN. */
    double r = num / (den > 1e-300 ? den : 1e-300);
    return num > 0 ? (r < 1e300 ? r : 1e300) : 1.0; /* (the clamp: no inf from a large num over a 0 den) */
}

/* Beyond TC_FAR_MOMENT times the cage's radius from its centre, mean value weights are normalised by
 * their first moment (tc_mv_total): there the sum has lost more than eps * TC_FAR_MOMENT to
 * cancellation, and the moment's own error (a partition of unity off by eps * distance / size, which
 * moves a cage far from the origin) is no larger. */
#define TC_FAR_MOMENT 1e3

/* The centre (bounding-box middle) c (D,) of vertices P (component k of vertex v at P[v * sv + k * sc])
 * and the square of TC_FAR_MOMENT times their largest distance from it. */
static inline double tc_far_centre(const double *P, long V, long sv, long sc, int D, double *c) {
    double r2 = 0.0;
    for (int k = 0; k < D; ++k) {
        double lo = P[k * sc], hi = lo;
        for (long v = 1; v < V; ++v) {
            double t = P[v * sv + k * sc];
            lo = t < lo ? t : lo;
            hi = t > hi ? t : hi;
        }
        c[k] = 0.5 * (lo + hi);
    }
    for (long v = 0; v < V; ++v) {
        double d2 = 0.0;
        for (int k = 0; k < D; ++k) d2 += (P[v * sv + k * sc] - c[k]) * (P[v * sv + k * sc] - c[k]);
        r2 = d2 > r2 ? d2 : r2;
    }
    return TC_FAR_MOMENT * TC_FAR_MOMENT * r2;
}

/* The normaliser of mean value weights w (V,) at x: their sum, or far from the cage (|x - c|^2 >
 * far2) the first moment (sum_v w_v (P_v - c)) . (x - c) / |x - c|^2, equal to it by linear
 * precision: the sum cancels to (size / distance) of its terms there, the moment does not (torch:
 * _core/common.py, normalise_weights). */
static inline double tc_mv_total(const double *w, long V, const double *P, long sv, long sc, int D, const double *x,
                                 const double *c, double far2) {
    double y[3] = {0, 0, 0}, y2 = 0.0;
    for (int k = 0; k < D; ++k) {
        y[k] = x[k] - c[k];
        y2 += y[k] * y[k];
    }
    double total = 0.0;
    if (!(y2 > far2)) {
        for (long v = 0; v < V; ++v) total += w[v];
        return total;
    }
    for (long v = 0; v < V; ++v) {
        double m = 0.0;
        for (int k = 0; k < D; ++k) m += (P[v * sv + k * sc] - c[k]) * y[k];
        total += w[v] * m;
    }
    return total / y2;
}

/* Stable split form of one triangle's mean value weights near its support plane (mvc3d.c). */
void tc_stable_face(double h, const double *s, const double *dots, const double *R, const double *ell,
                    const double *gram, double two_area, double *w);

/* Green integrals of one triangle, and its per-face constants (gc3d.c). */
int tc_tri_green(const double a[3][3], const double *nf, double two_area, const double *ell, const double *edir,
                 const double *eout, const double *gbary, double tol, double *phi, double *psi, double *omega,
                 double *alpha);
double tc_tri_frame(const double a[3][3], double *nf, double *ell, double *edir, double *eout, double *gbary);

/* A set of triangles for tc_gc_point (gc3d.c; layouts as tc_gc3d's arguments); fc: per-face
 * constants that tc_gc_prepare folds (tc_gc_free releases them). */
typedef struct {
    const double *Pv;
    long V;
    const int *tri;
    long T;
    const int *edges;
    long E;
    const double *eu;
    const int *fe;
    const double *nrm, *two_area, *ell, *edir, *eout, *gbary;
    double *fc;
    long *thin; /* the faces tc_thin_face flags, nthin of them (tc_gc_prepare) */
    long nthin;
    /* The far-field rule (torchcage/families/green/far_triangle.py; Q = 0: none): the faces' longest
     * edges (T,), the Q nodes of each face (T, Q, 3), their weights with the area (T, Q) and
     * barycentric coordinates (Q, 3); a pair takes it when its nearest corner is far_c longest
     * edges away or more. */
    const double *longest, *far_nodes, *far_w, *far_bary;
    long Q;
    double far_c;
} gc_tables;
/* Whether face f of g is seen from far by a point whose distances to the face's corners are R (3,). */
int tc_far_pair(const gc_tables *g, long f, const double *R);
/* Face f's integrals by the far-field rule, seen from x with signed distance h: phi (3,) (with
 * 1 / 4 pi, may be NULL), psi, omega, K (3,) (may be NULL) and, when gom is not NULL, the gradients
 * gom (3,) of omega and gK (3, 3) of K (gK[3 a + b] = d K_a / d x_b). */
void tc_far_face(const gc_tables *g, long f, const double *x, double h, double *phi, double *psi, double *omega,
                 double *K, double *gom, double *gK);
/* Thin faces (torchcage/_core/thin_triangle.py): THIN_ASPECT times longer than wide, seen from
 * THIN_DISTANCE widths or more from their longest edge, take the swept forms. */
#define TC_THIN_ASPECT 100.0
#define TC_THIN_DISTANCE 9.0
int tc_thin_face(const double a[3][3], double two_area);
/* The derivatives of mean value coordinates at a point on the cage (an edge: two faces) are those of
 * the interpolant of the largest face holding it; of faces whose areas are within this relative
 * margin, the first (kernel3d.AREA_TIE: the kernels' areas differ in their last digits, and a
 * triangulated quad's two halves often tie). */
#define TC_AREA_TIE 1e-9
/* Whether the foot point of a point (corners a = p_i - x) lies in the face of unit normal n and
 * edge lengths ell, within tol: n . (a_j x a_k) >= -tol ell_e for every edge (mvcd3d.c). */
int tc_in_face_prism(const double a[3][3], const double *n, const double *ell, double tol);
/* Mean value weights (w) of a thin face with their gradients (g) and Hessians (H, upper triangle) in
 * the point, by the swept form (mvcd3d.c). Returns 1. */
int tc_thin_mvc(const double a[3][3], const double *n, double h, double two_area, double *w, double g[3][3],
                 double H[3][6]);
int tc_thin_green(const double a[3][3], double h, double two_area, double *phi, double *psi, double *omega);
int tc_gc_prepare(gc_tables *g); /* 0: not allocated (the caller marks its outputs NaN) */
void tc_gc_free(gc_tables *g);
size_t tc_gc_workspace(const gc_tables *g);
long tc_gc_point(const gc_tables *g, const double *x, double tol, double *ws, double *psi, double *P, double *OM,
                 double *on_alpha);

/* Per point-quad quantities of quad mean value and quad Green coordinates (qmvc3d.c). */
typedef struct {
    double p[4][3], R[4], m[3], k[4], rows[4][3], b[3], cc[3], dd[3];
    double D, kabs, u, v;
    int flat, inside, vertex, on;
} quad_pair;
/* The per-quad part of the pair quantities (independent of the point): tc_quad_const once per quad,
 * then tc_quad_pair_c per point. */
typedef struct {
    double b[3], cc[3], dd[3], N0[3], Nu[3], Nv[3], nq[3], area2, hull_two_area[4];
} quad_const;
void tc_quad_const(const double *P, const int *qi, quad_const *qc);
void tc_quad_pair_c(const double *P, const int *qi, const quad_const *qc, const double *x, double tol, int project,
                    quad_pair *qp);
/* QL points for one quad side by side (the Riemann form: project on), tc_quad_pair_c's steps lane by lane
 * (the same operations in the same order, so the same bits); the lanes it cannot serve (on a corner, on a
 * flat quad's plane, outside the tetrahedron with a hull face near its plane) are marked redo, for
 * tc_quad_pair_c. X: the block's nl <= QL points (the lanes past nl repeat the first). */
#define QL 8 /* (8 measured 6-8% faster than 4 with AVX2, one thread, in QMVC) */
typedef struct {
    double p[4][3][QL], R[4][QL], m[3][QL], k[4][QL], rows[4][3][QL], D[QL], kabs[QL], u[QL], v[QL];
    int inside[QL], on[QL], redo[QL];
} quad_lanes;
void tc_quad_pair_lanes(const double *P, const int *qi, const quad_const *qc, const double *X, int nl, double tol,
                        quad_lanes *L);

/* The four corner integrals of a bilinear quad (xi - x = p0 + u b + v cc + u v dd) to the relative
 * tolerance tol (quadrature.c), or with green the eight of quad Green coordinates (without 1 / 4 pi);
 * the first split at (us, vs); on: the point is at xi(us, vs) (principal values); gl: Gauss-Legendre
 * nodes and weights on [0, 1], (TC_QMAX_ORDER + 1, 2, TC_QMAX_ORDER). */
#define TC_QMAX_ORDER 16 /* MAX_ORDER in _quad_quadrature.py */
void tc_quad_integrals(const double *p0, const double *b, const double *cc, const double *dd, double us, double vs,
                       int on, double tol, const double *gl, int green, double *om);
/* 1 if tc_quad_integrals takes the quad qi of P (seen from x) as one panel, without splitting it. */
int tc_quad_whole(const double *P, const int *qi, const double *x, double tol);

#endif
