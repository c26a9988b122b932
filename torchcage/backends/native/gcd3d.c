/*
 * Native CPU kernel of the derivatives of 3D Green coordinates with respect to the points (float64):
 * the closed forms of torchcage/families/green/derivatives3d.py (see its module docstring), one
 * point per iteration on top of tc_gc_point (gc3d.c), which supplies each face's solid angle and
 * the edge integrals; OpenMP over points. The tests check it against the torch kernel and 60-digit
 * differences.
 */
#define _GNU_SOURCE
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "native.h"

#define FOUR_PI 12.566370614359172953850573533118

/* One edge's terms: the gradient gI (3) of I = int_e dl / r and the Biot-Savart term B (3) (their
 * sum over a face's edges is the gradient of its solid angle), for the edge from a_j to a_k (corners
 * minus the point) with unit direction u and the corners' distances R_j, R_k. */
static inline void edge_terms(const double *aj, const double *ak, double Rj, double Rk, const double *u, double *gI,
                              double *B) {
    double lj = dot3(aj, u), lk = dot3(ak, u);
    /* the perpendicular from the point to the edge's line, from the nearer end (the values' kernel's) */
    double m[3];
    for (int c = 0; c < 3; ++c) m[c] = Rj < Rk ? aj[c] : (Rk < Rj ? ak[c] : 0.5 * (aj[c] + ak[c]));
    double mu = dot3(m, u), w[3] = {m[0] - mu * u[0], m[1] - mu * u[1], m[2] - mu * u[2]};
    double cc;
    if (lj >= 0 || lk <= 0) { /* both ends on one side of the foot: the form that does not cancel */
        double den = (lk * Rj + lj * Rk) * Rj * Rk;
        cc = den != 0 ? (lk - lj) * (lk + lj) / den : 0.0;
    } else {
        double den = dot3(w, w);
        cc = den != 0 ? (lk / Rk - lj / Rj) / den : 0.0;
    }
    double s = 1.0 / Rj - 1.0 / Rk, wu[3];
    cross3(w, u, wu);
    for (int c = 0; c < 3; ++c) {
        gI[c] = u[c] * s + w[c] * cc;
        B[c] = wu[c] * cc;
    }
}

/*
 * Layouts as tc_gc3d's (gc3d.c). Outputs, per point: GPHI (n, V, 3), GPSI (n, T, 3) and, for order 2,
 * HPHI (n, V, 3, 3), HPSI (n, T, 3, 3) (symmetric). OK (n,) is 1 where the closed form served; 0 for a
 * point on the cage or beside a thin face seen from a few widths, whose rows are left zero for the
 * caller to fill (it differentiates the torch kernel there).
 */
void tc_gcd3d(const double *Pv, long V, const int *tri, long T, const int *edges, long E, const double *eu,
              const int *fe, const double *nrm, const double *two_area, const double *ell, const double *edir,
              const double *eout, const double *gbary, const double *longest, const double *far_nodes,
              const double *far_w, const double *far_bary, long Q, double far_c, const double *X, long n, double tol,
              int order, int nthreads, double *GPHI, double *GPSI, double *HPHI, double *HPSI, int *OK) {
    gc_tables g = {Pv,   V,    tri,  T,       edges,     E,    eu,       fe, nrm, two_area, ell, edir, eout,
                   gbary, NULL, NULL, 0,       longest,   far_nodes, far_w, far_bary, Q, far_c};
    int failed = !tc_gc_prepare(&g); /* a workspace not allocated: every output NaN (the glue raises) */
    const double inv4pi = 1.0 / FOUR_PI;
#pragma omp parallel num_threads(nthreads)
    {
        size_t wsn = tc_gc_workspace(&g);
        double *buf = (double *)malloc(sizeof(double) * (wsn + 5 * (size_t)T));
        if (buf == NULL) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp barrier
        if (failed) goto done; /* (every thread: none enters the worksharing loop) */
        double *P = buf + wsn, *OM = P + 3 * T, *psi = OM + T;
#pragma omp for schedule(dynamic, 16)
        for (long p = 0; p < n; ++p) {
            double on_alpha[3];
            double *gphi = GPHI + p * V * 3, *gpsi = GPSI + p * T * 3;
            double *hphi = order == 2 ? HPHI + p * V * 9 : NULL, *hpsi = order == 2 ? HPSI + p * T * 9 : NULL;
            memset(gphi, 0, sizeof(double) * 3 * (size_t)V);
            memset(gpsi, 0, sizeof(double) * 3 * (size_t)T);
            if (hphi) {
                memset(hphi, 0, sizeof(double) * 9 * (size_t)V);
                memset(hpsi, 0, sizeof(double) * 9 * (size_t)T);
            }
            long on_face = tc_gc_point(&g, X + 3 * p, tol, buf, psi, P, OM, on_alpha);
            const double *Ax = buf, *Ay = Ax + V, *Az = Ay + V, *RA = Az + V, *IE = RA + V;
            int ok = on_face < 0;
            for (long q = 0; ok && q < g.nthin; ++q) { /* a thin face seen from a few widths: K cancels */
                long f = g.thin[q];
                double a[3][3];
                for (int i = 0; i < 3; ++i) {
                    int v = tri[i * T + f];
                    a[i][0] = Ax[v], a[i][1] = Ay[v], a[i][2] = Az[v];
                }
                double R[3] = {RA[tri[f]], RA[tri[T + f]], RA[tri[2 * T + f]]};
                if (tc_thin_face(a, two_area[f]) && !tc_far_pair(&g, f, R)) ok = 0; /* (far: the Gauss rule) */
            }
            OK[p] = ok;
            if (!ok) continue;
            for (long f = 0; f < T; ++f) {
                if (!(two_area[f] > 0)) continue; /* a degenerate face integrates to nothing */
                const double *nf = nrm + 3 * f, *mo = eout + 9 * f, *gb = gbary + 9 * f, *ed = edir + 9 * f;
                double om = OM[f], K[3] = {0.0, 0.0, 0.0}, fgom[3], fgK[9];
                const double Rf[3] = {RA[tri[f]], RA[tri[T + f]], RA[tri[2 * T + f]]};
                int far = tc_far_pair(&g, f, Rf);
                if (far) { /* seen from far: Omega, K and their gradients by the Gauss rule */
                    int v0 = tri[f];
                    double h = Ax[v0] * nf[0] + Ay[v0] * nf[1] + Az[v0] * nf[2], ps;
                    tc_far_face(&g, f, X + 3 * p, h, NULL, &ps, &om, K, hphi ? fgom : NULL, fgK);
                } else {
                    for (int e = 0; e < 3; ++e) {
                        double I = IE[fe[e * T + f]];
                        for (int c = 0; c < 3; ++c) K[c] -= mo[3 * e + c] * I;
                    }
                }
                for (int c = 0; c < 3; ++c) gpsi[3 * f + c] = (K[c] + om * nf[c]) * inv4pi;
                for (int i = 0; i < 3; ++i) {
                    double *gv = gphi + 3 * (long)tri[i * T + f], gK = dot3(gb + 3 * i, K);
                    for (int c = 0; c < 3; ++c) gv[c] += (om * gb[3 * i + c] - nf[c] * gK) * inv4pi;
                }
                if (!hphi) continue;
                /* Hessians: the gradients of the edge integrals and of the solid angle (far: the rule's) */
                double Bsum[3] = {0.0, 0.0, 0.0}, gK[3][3]; /* gK[a][b] = d K_a / d x_b */
                if (far) {
                    for (int c = 0; c < 3; ++c) {
                        Bsum[c] = fgom[c];
                        for (int d = 0; d < 3; ++d) gK[c][d] = fgK[3 * c + d];
                    }
                } else {
                    double a[3][3], R[3], gI[3][3], B[3];
                    for (int i = 0; i < 3; ++i) {
                        int v = tri[i * T + f];
                        a[i][0] = Ax[v], a[i][1] = Ay[v], a[i][2] = Az[v], R[i] = RA[v];
                    }
                    for (int e = 0; e < 3; ++e) {
                        int j = (e + 1) % 3, k = (e + 2) % 3;
                        edge_terms(a[j], a[k], R[j], R[k], ed + 3 * e, gI[e], B);
                        for (int c = 0; c < 3; ++c) Bsum[c] += B[c];
                    }
                    for (int ia = 0; ia < 3; ++ia)
                        for (int ib = 0; ib < 3; ++ib)
                            gK[ia][ib] = -(mo[ia] * gI[0][ib] + mo[3 + ia] * gI[1][ib] + mo[6 + ia] * gI[2][ib]);
                }
                double *hs = hpsi + 9 * f;
                for (int ia = 0; ia < 3; ++ia)
                    for (int ib = 0; ib < 3; ++ib) hs[3 * ia + ib] = (gK[ia][ib] + nf[ia] * Bsum[ib]) * inv4pi;
                for (int ia = 0; ia < 3; ++ia) /* a face's potential is smooth off the face: symmetric */
                    for (int ib = ia + 1; ib < 3; ++ib) hs[3 * ia + ib] = hs[3 * ib + ia] = 0.5 * (hs[3 * ia + ib] + hs[3 * ib + ia]);
                for (int i = 0; i < 3; ++i) {
                    const double *gi = gb + 3 * i;
                    double v[3];
                    for (int ib = 0; ib < 3; ++ib) v[ib] = gi[0] * gK[0][ib] + gi[1] * gK[1][ib] + gi[2] * gK[2][ib];
                    double *hv = hphi + 9 * (long)tri[i * T + f];
                    for (int ia = 0; ia < 3; ++ia)
                        for (int ib = 0; ib < 3; ++ib) hv[3 * ia + ib] += (gi[ia] * Bsum[ib] - nf[ia] * v[ib]) * inv4pi;
                }
            }
            if (hphi) /* symmetric once summed over the cage */
                for (long v = 0; v < V; ++v) {
                    double *hv = hphi + 9 * v;
                    for (int ia = 0; ia < 3; ++ia)
                        for (int ib = ia + 1; ib < 3; ++ib) hv[3 * ia + ib] = hv[3 * ib + ia] = 0.5 * (hv[3 * ia + ib] + hv[3 * ib + ia]);
                }
        }
    done:
        free(buf);
    }
    if (failed)
        for (long k = 0; k < n * V * 3; ++k) GPHI[k] = NAN;
    tc_gc_free(&g);
}
