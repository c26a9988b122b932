/*
 * Native CPU rasteriser of torchcage.image's forward mapping: which triangle of a deformed pixel
 * mesh covers each output pixel centre. Only the discrete choice is made here; torchcage.image
 * recomputes the barycentric coordinates in torch, so that gradients flow to the mesh.
 */
#include <math.h>

/*
 * P: (B, Nv, 2) float64 mesh vertex positions (x, y) in pixels; tri: (T, 3) int32 triangles;
 * S: (Nv, C) float64 values at the mesh vertices.
 * Output out: (B, H, W) int32, the index of the last triangle (in order) whose closed interior holds
 * the pixel centre (x = column, y = row), -1 where none does; val: (B, H, W, C) the linear
 * interpolation of S in that triangle (untouched where out is -1). OpenMP over the batch and rows.
 */
void tc_raster2d(const double *P, long B, long Nv, const int *tri, long T, long H, long W, const double *S, long C,
                 int nthreads, int *out, double *val) {
    for (long i = 0; i < B * H * W; ++i) out[i] = -1;
    const long nb = (nthreads + B - 1) / B; /* bands of rows per image, so that every thread has work */
#pragma omp parallel for num_threads(nthreads) schedule(static) collapse(2)
    for (long b = 0; b < B; ++b) {
        for (long band = 0; band < nb; ++band) {
            /* each thread owns a band of rows, so writes never race and later triangles win */
            const long r0 = band * H / nb, r1 = (band + 1) * H / nb;
            const double *Pb = P + b * Nv * 2;
            int *ob = out + b * H * W;
            for (long t = 0; t < T; ++t) {
                const int ia = tri[3 * t], ib = tri[3 * t + 1], ic = tri[3 * t + 2];
                const double ax = Pb[2 * ia], ay = Pb[2 * ia + 1], bx = Pb[2 * ib], by = Pb[2 * ib + 1];
                const double cx = Pb[2 * ic], cy = Pb[2 * ic + 1];
                double ymin = ay < by ? ay : by, ymax = ay > by ? ay : by;
                ymin = ymin < cy ? ymin : cy;
                ymax = ymax > cy ? ymax : cy;
                long y0 = (long)ceil(ymin), y1 = (long)floor(ymax);
                if (y0 < r0) y0 = r0;
                if (y1 > r1 - 1) y1 = r1 - 1;
                if (y0 > y1) continue;
                double xmin = ax < bx ? ax : bx, xmax = ax > bx ? ax : bx;
                xmin = xmin < cx ? xmin : cx;
                xmax = xmax > cx ? xmax : cx;
                long x0 = (long)ceil(xmin), x1 = (long)floor(xmax);
                if (x0 < 0) x0 = 0;
                if (x1 > W - 1) x1 = W - 1;
                if (x0 > x1) continue;
                const double area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax);
                if (area == 0.0) continue;
                const double s = area > 0 ? 1.0 : -1.0;
                for (long y = y0; y <= y1; ++y) {
                    for (long x = x0; x <= x1; ++x) {
                        const double e0 = s * ((bx - ax) * (y - ay) - (by - ay) * (x - ax));
                        const double e1 = s * ((cx - bx) * (y - by) - (cy - by) * (x - bx));
                        const double e2 = s * ((ax - cx) * (y - cy) - (ay - cy) * (x - cx));
                        if (e0 >= 0 && e1 >= 0 && e2 >= 0) {
                            const long o = y * W + x;
                            const double la = e1 / (s * area), lb = e2 / (s * area), lc = 1.0 - la - lb;
                            double *vo = val + (b * H * W + o) * C;
                            ob[o] = (int)t;
                            for (long k = 0; k < C; ++k) vo[k] = la * S[ia * C + k] + lb * S[ib * C + k] + lc * S[ic * C + k];
                        }
                    }
                }
            }
        }
    }
}
