/*
 * Native CPU kernel of torchcage.geometry.winding_number (float64): the generalised winding number
 * of a closed triangle surface, the sum over triangles of Van Oosterom and Strackee's signed solid
 * angle over 4 pi, one point per iteration, OpenMP over points, a vectorised loop over triangles.
 */
#define _GNU_SOURCE
#include <math.h>

#include "native.h"

#ifdef TC_LIBMVEC
__attribute__((simd("notinbranch"))) double atan2(double, double);
#endif

/* P (T, 3, 3) triangle corners (outward oriented); X (n, 3); W (n,) out. */
void tc_winding3d(const double *P, long T, const double *X, long n, int nthreads, double *W) {
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (long p = 0; p < n; ++p) {
        const double x0 = X[3 * p], x1 = X[3 * p + 1], x2 = X[3 * p + 2];
        double sum = 0.0;
#pragma omp simd reduction(+ : sum)
        for (long t = 0; t < T; ++t) {
            const double *q = P + 9 * t;
            double ax = q[0] - x0, ay = q[1] - x1, az = q[2] - x2;
            double bx = q[3] - x0, by = q[4] - x1, bz = q[5] - x2;
            double cx = q[6] - x0, cy = q[7] - x1, cz = q[8] - x2;
            double la = sqrt(ax * ax + ay * ay + az * az), lb = sqrt(bx * bx + by * by + bz * bz);
            double lc = sqrt(cx * cx + cy * cy + cz * cz);
            double det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx);
            double den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la +
                         (cx * ax + cy * ay + cz * az) * lb;
            sum += atan2(det, den);
        }
        W[p] = sum / (2.0 * 3.14159265358979323846);
    }
}
