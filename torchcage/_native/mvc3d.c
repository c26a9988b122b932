/*
 * Native CPU kernel of torchcage's 3D mean value weights (float64).
 *
 * The same formulas as torchcage/functional/mean_value.py (see its module docstring): the direct
 * vector form away from a face's support plane, the stable split form near it, and the
 * interpolating values for points on the cage. One point per iteration, OpenMP over points.
 * The tests check this kernel against the torch kernel and an mpmath reference.
 */
#define _GNU_SOURCE
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define TWO_PI 6.283185307179586476925286766559

#ifdef TC_LIBMVEC
/* Let the compiler call glibc's vector atan (libmvec, max error 4 ulp) in the edge loop. */
__attribute__((simd("notinbranch"))) double atan(double);
#endif

static inline void cross3(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static inline double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* Stable split form of one face's weights (see _stable_face_weights in mean_value.py). */
static void stable_face(double h, const double *s, const double *dots, const double *R, const double *ell,
                        const double *gram, double two_area, double *w) {
    double h2 = h * h, wind_angle = 0.0, S_rest = 0.0, tN[3];
    for (int e = 0; e < 3; ++e) {
        int j = (e + 1) % 3, k = (e + 2) % 3;
        double s_abs = fabs(s[e]);
        double sigma = s[e] >= 0 ? 1.0 : -1.0;
        double qq = dots[e] - h2;
        double N = sqrt(s[e] * s[e] + h2 * ell[e] * ell[e]);
        double theta0 = qq > 0 ? atan(s_abs / qq) : M_PI / 2 - atan(qq / (s_abs > 0 ? s_abs : 1e-300));
        wind_angle += sigma * theta0;
        double Nps = N + s_abs;
        double safe_Nps = Nps > 0 ? Nps : 1.0;
        double X = qq * ell[e] * ell[e] / safe_Nps - s_abs;
        double Y = dots[e] * qq + N * s_abs;
        double delta = Y > 0 ? atan(h2 * X / Y) : atan2(h2 * X, Y);
        double delta_h2 = h2 > 0 ? delta / h2 : X / Y;
        double theta = theta0 + delta;
        double safe_N = N > 0 ? N : 1.0;
        tN[e] = N > 0 ? theta / safe_N : 1.0 / (R[j] * R[k]);
        double eps_h2 = ell[e] * ell[e] / (safe_N * safe_Nps);
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
 * P: (V, 3) vertices; tri: (T, 3) corners; fe: (T, 3) index of the edge opposite each corner in
 * the edge list edges: (E, 2), stored as (t[i+1], t[i+2]) when fs = +1 and reversed when -1;
 * nrm: (T, 3) unit normals; two_area: (T,); ell: (T, 3) length of the edge opposite each corner;
 * gram: (T, 3, 3) E_i . E_e; far_nodes (T, Q, 3) and far_coef (T, Q, 3): the far-field rule,
 * used for points whose face weights sum in absolute value to more than cancel_c times their total,
 * on faces whose longest edge (longest: (T,)) is below far_c times the distance; X: (n, 3) points. Output W: (n, V) normalised coordinates (on[p] = 1
 * marks points on the cage, which get their interpolating values).
 */
void tc_mvc3d(const double *P, long V, const long *tri, long T, const long *edges, long E, const long *fe,
              const double *fs, const double *nrm, const double *two_area, const double *ell, const double *gram,
              const double *far_nodes, const double *far_coef, const double *longest, long Q, double far_c,
              double cancel_c,
              const double *X, long n, double tol, double near_c, int nthreads, double *W, unsigned char *on) {
#pragma omp parallel num_threads(nthreads)
    {
        double *A = (double *)malloc(sizeof(double) * 3 * (size_t)V);
        double *RA = (double *)malloc(sizeof(double) * (size_t)V);
        double *EN = (double *)malloc(sizeof(double) * 8 * (size_t)E); /* N(3), gN(3), |N|, a.b */
        double *ARG = (double *)malloc(sizeof(double) * (size_t)E);
        double *FW = (double *)malloc(sizeof(double) * 3 * (size_t)T); /* this point's face weights */
#pragma omp for schedule(dynamic, 64)
        for (long p = 0; p < n; ++p) {
            const double *x = X + 3 * p;
            double *w = W + p * V;
            memset(w, 0, sizeof(double) * (size_t)V);
            on[p] = 0;
            double abs_sum = 0.0;
            for (long v = 0; v < V; ++v) {
                double *av = A + 3 * v;
                av[0] = P[3 * v] - x[0];
                av[1] = P[3 * v + 1] - x[1];
                av[2] = P[3 * v + 2] - x[2];
                RA[v] = sqrt(dot3(av, av));
            }
            /* Edges in three passes so that the atan pass vectorises: N, |N|, a.b and the atan argument;
             * atan; the scaled normal g N with g = theta / (2 |N|). */
            for (long q = 0; q < E; ++q) {
                long j = edges[2 * q], k = edges[2 * q + 1];
                double *en = EN + 8 * q;
                cross3(A + 3 * j, A + 3 * k, en);
                double Nn = sqrt(dot3(en, en)), d = dot3(A + 3 * j, A + 3 * k), RR = RA[j] * RA[k];
                en[6] = Nn;
                en[7] = d;
                ARG[q] = d >= 0 ? Nn / (RR + d) : Nn / (RR - d);
            }
#pragma omp simd
            for (long q = 0; q < E; ++q) ARG[q] = atan(ARG[q]);
            for (long q = 0; q < E; ++q) {
                double *en = EN + 8 * q;
                double Nn = en[6], th = en[7] >= 0 ? 2.0 * ARG[q] : M_PI - 2.0 * ARG[q];
                double g = Nn > 0 ? 0.5 * th / Nn : 0.5 / (RA[edges[2 * q]] * RA[edges[2 * q + 1]]);
                en[3] = g * en[0];
                en[4] = g * en[1];
                en[5] = g * en[2];
            }
            for (long f = 0; f < T; ++f) {
                const long *t = tri + 3 * f;
                double R[3] = {RA[t[0]], RA[t[1]], RA[t[2]]};
                const double *nf = nrm + 3 * f;
                const double *lf = ell + 3 * f;
                const double *en[3] = {EN + 8 * fe[3 * f], EN + 8 * fe[3 * f + 1], EN + 8 * fe[3 * f + 2]};
                const double *sg = fs + 3 * f;
                double h = dot3(A + 3 * t[0], nf);
                double rmin = fmin(fmin(R[0], R[1]), R[2]);
                double wf[3];
                if (fabs(h) >= near_c * rmin && rmin > tol) {
                    /* Direct vector form: w_i = N_i . m / (2 A h), m = sum_e g_e N_e. */
                    double m[3];
                    for (int c = 0; c < 3; ++c) m[c] = sg[0] * en[0][3 + c] + sg[1] * en[1][3 + c] + sg[2] * en[2][3 + c];
                    double inv_det = 1.0 / (two_area[f] * h);
                    for (int i = 0; i < 3; ++i) wf[i] = sg[i] * dot3(en[i], m) * inv_det;
                } else {
                    double s[3], dots[3];
                    for (int e = 0; e < 3; ++e) {
                        s[e] = sg[e] * dot3(en[e], nf);
                        dots[e] = en[e][7];
                    }
                    if ((fabs(h) <= tol && s[0] >= -tol * lf[0] && s[1] >= -tol * lf[1] && s[2] >= -tol * lf[2]) ||
                        rmin <= tol) {
                        /* On the face (or a vertex): barycentric (Lagrange) values, nothing else counts. */
                        double b[3];
                        for (int i = 0; i < 3; ++i)
                            b[i] = rmin <= tol ? (R[i] <= tol ? 1.0 : 0.0) : (s[i] > 0 ? s[i] : 0.0);
                        double sum = b[0] + b[1] + b[2];
                        memset(w, 0, sizeof(double) * (size_t)V);
                        for (int i = 0; i < 3; ++i) w[t[i]] += b[i] / sum;
                        on[p] = 1;
                        break;
                    }
                    stable_face(h, s, dots, R, lf, gram + 9 * f, two_area[f], wf);
                }
                w[t[0]] += wf[0];
                w[t[1]] += wf[1];
                w[t[2]] += wf[2];
                FW[3 * f] = wf[0];
                FW[3 * f + 1] = wf[1];
                FW[3 * f + 2] = wf[2];
                abs_sum += fabs(wf[0] + wf[1] + wf[2]);
            }
            double total = 0.0;
            if (!on[p]) {
                for (long v = 0; v < V; ++v) total += w[v];
            }
            if (!on[p] && abs_sum > cancel_c * fabs(total)) {
                /* The face weights cancel (far outside): redo faces seen small by quadrature,
                 * w_i = h * sum_q c_qi / |p_q - x|^4. */
                for (long f = 0; f < T; ++f) {
                    const long *t = tri + 3 * f;
                    double rmin = fmin(fmin(RA[t[0]], RA[t[1]]), RA[t[2]]);
                    if (!(longest[f] < far_c * rmin)) continue;
                    const double *nq = far_nodes + 3 * Q * f, *cq = far_coef + 3 * Q * f;
                    double acc0 = 0.0, acc1 = 0.0, acc2 = 0.0;
                    for (long k = 0; k < Q; ++k) {
                        double d0 = nq[3 * k] - x[0], d1 = nq[3 * k + 1] - x[1], d2 = nq[3 * k + 2] - x[2];
                        double r2 = d0 * d0 + d1 * d1 + d2 * d2, inv = 1.0 / (r2 * r2);
                        acc0 += cq[3 * k] * inv;
                        acc1 += cq[3 * k + 1] * inv;
                        acc2 += cq[3 * k + 2] * inv;
                    }
                    double h = dot3(A + 3 * t[0], nrm + 3 * f);
                    w[t[0]] += h * acc0 - FW[3 * f];
                    w[t[1]] += h * acc1 - FW[3 * f + 1];
                    w[t[2]] += h * acc2 - FW[3 * f + 2];
                }
                total = 0.0;
                for (long v = 0; v < V; ++v) total += w[v];
            }
            if (!on[p]) {
                double inv = 1.0 / total;
                for (long v = 0; v < V; ++v) w[v] *= inv;
            }
        }
        free(A);
        free(RA);
        free(EN);
        free(ARG);
        free(FW);
    }
}
