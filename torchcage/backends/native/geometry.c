/*
 * Native CPU kernels of torchcage.geometry (float64), OpenMP over points:
 * - tc_winding3d (winding_number): the generalised winding number of a closed triangle surface,
 *   the sum over triangles of Van Oosterom and Strackee's signed solid angle over 4 pi, a
 *   vectorised loop over triangles;
 * - tc_nearest3d (nearest_triangle): the distance to the nearest triangle of a soup, less a
 *   per-triangle slack, and that triangle's index.
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

/* Squared distance from the origin to segment a -> a + e. */
static inline double tc_segment2(double ax, double ay, double az, double ex, double ey, double ez) {
    double ee = ex * ex + ey * ey + ez * ez;
    double t = ee > 0.0 ? -(ax * ex + ay * ey + az * ez) / ee : 0.0;
    t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
    double dx = ax + t * ex, dy = ay + t * ey, dz = az + t * ez;
    return dx * dx + dy * dy + dz * dz;
}

/* P (T, 3, 3) triangle corners; S (T,) slack subtracted from each triangle's distance (may be NULL);
 * X (n, 3); D (n,) out: min over triangles of |x - triangle| - S (NaN where a NaN takes part); I (n,)
 * out: its triangle (-1 when T = 0). A triangle's distance is to its plane where the point projects inside it, else to its
 * nearest edge (degenerate triangles: edges only). */
void tc_nearest3d(const double *P, long T, const double *S, const double *X, long n, int nthreads, double *D,
                  int *I) {
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (long p = 0; p < n; ++p) {
        const double x0 = X[3 * p], x1 = X[3 * p + 1], x2 = X[3 * p + 2];
        double best = INFINITY;
        int at = -1;
        for (long t = 0; t < T; ++t) {
            const double *q = P + 9 * t;
            double ax = q[0] - x0, ay = q[1] - x1, az = q[2] - x2;
            double bx = q[3] - x0, by = q[4] - x1, bz = q[5] - x2;
            double cx = q[6] - x0, cy = q[7] - x1, cz = q[8] - x2;
            double e0x = bx - ax, e0y = by - ay, e0z = bz - az; /* a -> b */
            double e1x = cx - bx, e1y = cy - by, e1z = cz - bz; /* b -> c */
            double e2x = ax - cx, e2y = ay - cy, e2z = az - cz; /* c -> a */
            double nx = e0y * (-e2z) - e0z * (-e2y), ny = e0z * (-e2x) - e0x * (-e2z), nz = e0x * (-e2y) - e0y * (-e2x);
            double nn = nx * nx + ny * ny + nz * nz;
            /* the point (the origin) projects inside when it is left of every edge seen along n:
             * n . (e x (o - a)) >= 0, i.e. s = n . (e x a) <= 0 with a the edge's start */
            double s0 = nx * (e0y * az - e0z * ay) + ny * (e0z * ax - e0x * az) + nz * (e0x * ay - e0y * ax);
            double s1 = nx * (e1y * bz - e1z * by) + ny * (e1z * bx - e1x * bz) + nz * (e1x * by - e1y * bx);
            double s2 = nx * (e2y * cz - e2z * cy) + ny * (e2z * cx - e2x * cz) + nz * (e2x * cy - e2y * cx);
            double d2;
            if (nn > 0.0 && s0 <= 0.0 && s1 <= 0.0 && s2 <= 0.0) {
                double h = ax * nx + ay * ny + az * nz;
                d2 = h * h / nn;
            } else {
                double u = tc_segment2(ax, ay, az, e0x, e0y, e0z);
                double v = tc_segment2(bx, by, bz, e1x, e1y, e1z);
                double w = tc_segment2(cx, cy, cz, e2x, e2y, e2z);
                d2 = u < v ? (u < w ? u : w) : (v < w ? v : w);
            }
            double d = sqrt(d2) - (S ? S[t] : 0.0);
            /* a NaN point, corner or slack: the answer is NaN, as torch's min gives (the segment
             * minima above would drop a NaN edge) */
            const double any = ax + ay + az + bx + by + bz + cx + cy + cz; /* NaN if any one is */
            if (d != d || any != any) {
                best = NAN;
                at = (int)t;
                break;
            }
            if (d < best) {
                best = d;
                at = (int)t;
            }
        }
        D[p] = best;
        I[p] = at;
    }
}
