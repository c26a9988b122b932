/*
 * Native CPU kernel of torchcage's 3D Green coordinates (float64): the same closed forms as
 * torchcage/functional/_green3d.py (see its module docstring), one point per iteration, OpenMP
 * over points. The tests check it against the torch kernel.
 */
#define _GNU_SOURCE
#include <math.h>
#include <string.h>

#define FOUR_PI 12.566370614359172953850573533118

#include "native.h"

/* int_e dl / r along the edge from p_j to p_k, in the form that does not cancel. */
static inline double edge_integral(double l_j, double l_k, double R_j, double R_k, double R0sq) {
    if (l_j >= 0) return log((R_k + l_k) / fmax(R_j + l_j, 1e-300));
    if (l_k <= 0) return log((R_j - l_j) / fmax(R_k - l_k, 1e-300));
    return log((R_k + l_k) * (R_j - l_j) / fmax(R0sq, 1e-300));
}

/*
 * P: (T, 3, 3) corners; nrm: (T, 3) unit normals; two_area: (T,); ell: (T, 3) length of the edge
 * opposite each corner; edir, eout, gbary: (T, 3, 3) unit direction p_{i+1} -> p_{i+2} of that
 * edge, its outward in-plane normal, the in-plane gradient of corner i's hat function; tri: (T, 3)
 * int32 corners; X: (n, 3). Outputs PHI: (n, V), PSI: (n, T).
 */
void tc_gc3d(const double *P, const double *nrm, const double *two_area, const double *ell, const double *edir,
             const double *eout, const double *gbary, const int *tri, long T, long V, const double *X, long n,
             double tol, int nthreads, double *PHI, double *PSI) {
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 16)
    for (long p = 0; p < n; ++p) {
        const double *x = X + 3 * p;
        double *phi = PHI + p * V, *psi = PSI + p * T;
        memset(phi, 0, sizeof(double) * (size_t)V);
        double omega_sum = 0.0, on_alpha[3] = {0.0, 0.0, 0.0};
        long on_face = -1;
        for (long f = 0; f < T; ++f) {
            const double *pf = P + 9 * f, *nf = nrm + 3 * f;
            double a[3][3], R[3];
            for (int i = 0; i < 3; ++i) {
                for (int c = 0; c < 3; ++c) a[i][c] = pf[3 * i + c] - x[c];
                R[i] = sqrt(dot3(a[i], a[i]));
            }
            double h = dot3(a[0], nf), habs = fabs(h);
            int on_plane = habs <= tol, inside = 1;
            double d[3], I[3], beta = 0.0;
            for (int e = 0; e < 3; ++e) {
                int j = (e + 1) % 3, k = (e + 2) % 3;
                const double *u = edir + 9 * f + 3 * e, *m = eout + 9 * f + 3 * e;
                d[e] = dot3(a[j], m);
                double l_j = dot3(a[j], u), l_k = dot3(a[k], u), R0sq = d[e] * d[e] + h * h;
                beta += atan2(d[e] * l_k, R0sq + habs * R[k]) - atan2(d[e] * l_j, R0sq + habs * R[j]);
                I[e] = edge_integral(l_j, l_k, R[j], R[k], R0sq);
                inside &= d[e] >= -tol;
            }
            double omega = on_plane ? 0.0 : (h >= 0 ? beta : -beta);
            double K[3] = {0.0, 0.0, 0.0}, dI = 0.0;
            for (int e = 0; e < 3; ++e) {
                if (!on_plane)
                    for (int c = 0; c < 3; ++c) K[c] -= eout[9 * f + 3 * e + c] * I[e];
                if (d[e] != 0) dI += d[e] * I[e];
            }
            double alpha[3];
            for (int i = 0; i < 3; ++i) {
                alpha[i] = d[i] * ell[3 * f + i] / two_area[f];
                double gK = dot3(gbary + 9 * f + 3 * i, K);
                phi[tri[3 * f + i]] += (alpha[i] * omega + h * gK) / FOUR_PI;
            }
            psi[f] = (dI - h * omega) / FOUR_PI;
            omega_sum += omega;
            if (on_plane && inside && on_face < 0) {
                on_face = f;
                for (int i = 0; i < 3; ++i) on_alpha[i] = alpha[i] > 0 ? alpha[i] : 0.0;
            }
        }
        if (on_face >= 0) { /* the limit from inside: hat values with the jump weight */
            double sum = on_alpha[0] + on_alpha[1] + on_alpha[2], jump = 1.0 - omega_sum / FOUR_PI;
            for (int i = 0; i < 3; ++i) phi[tri[3 * on_face + i]] += jump * on_alpha[i] / sum;
        }
    }
}
