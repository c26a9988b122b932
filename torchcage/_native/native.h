/* Shared helpers of torchcage's native kernels (header-only, included by the .c files). */
#ifndef TORCHCAGE_NATIVE_H
#define TORCHCAGE_NATIVE_H

static inline void cross3(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static inline double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

/* Stable split form of one triangle's mean value weights near its support plane (mvc3d.c). */
void tc_stable_face(double h, const double *s, const double *dots, const double *R, const double *ell,
                    const double *gram, double two_area, double *w);

#endif
