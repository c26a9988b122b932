// torchcage benchmarks/peers: our driver around the QMVC authors' header-only C++
// (Thiery, Memari, Boubekeur 2018, "Mean value coordinates for quad cages in 3D";
// https://github.com/superboubek/QMVC). Their headers are read from the checkout the user names
// in TORCHCAGE_PEER_QMVC at build time (benchmarks/peers.py); nothing of theirs is in this
// repository. Each function converts the numpy arrays to the authors' types once, then calls
// their per-point function for every point, exactly as their viewer does, one thread.
#include <vector>
#include <cmath>
#include <cassert>

#include "point3.h"
#include "point4.h"
#include "mvc/mvc.h"
#include "gc/gc.h"
#include "qmvc/qmvc.h"

typedef std::vector<std::vector<int> > faces_t;

static std::vector<point3d> to_points(const double *xyz, long n) {
    std::vector<point3d> out((size_t)n);
    for (long i = 0; i < n; ++i) out[i] = point3d(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]);
    return out;
}

static faces_t to_faces(const long *idx, long n, int k) {
    faces_t out((size_t)n, std::vector<int>(k));
    for (long f = 0; f < n; ++f)
        for (int j = 0; j < k; ++j) out[f][j] = (int)idx[k * f + j];
    return out;
}

extern "C" {

int peer_abi_version(void) { return 1; }

// Mean value coordinates (their MVC3D::computeCoordinates, the "simple code" variant they ship
// as default). cage (V, 3), tris (T, 3), points (N, 3) -> out (N, V).
void peer_mvc(const double *cage, long nv, const long *tris, long nt, const double *pts, long n,
              double *out) {
    std::vector<point3d> verts = to_points(cage, nv);
    faces_t faces = to_faces(tris, nt, 3);
    std::vector<point3d> normals((size_t)nt);  // only its size is read
    std::vector<double> w;
    for (long i = 0; i < n; ++i) {
        point3d eta(pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]);
        MVC3D::computeCoordinates<int, double, point3d>(eta, faces, verts, normals, w);
        for (long v = 0; v < nv; ++v) out[i * nv + v] = w[v];
    }
}

// Green coordinates (their GreenCoordinates3D::URAGO::computeCoordinates).
// -> phi (N, V), psi (N, T) (psi multiplies the unit outward triangle normals).
void peer_gc(const double *cage, long nv, const long *tris, long nt, const double *pts, long n,
             double *phi, double *psi) {
    std::vector<point3d> verts = to_points(cage, nv);
    faces_t faces = to_faces(tris, nt, 3);
    std::vector<double> p, s;
    for (long i = 0; i < n; ++i) {
        point3d eta(pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]);
        GreenCoordinates3D::URAGO::computeCoordinates<int, double, point3d>(eta, faces, verts, p, s);
        for (long v = 0; v < nv; ++v) phi[i * nv + v] = p[v];
        for (long t = 0; t < nt; ++t) psi[i * nt + t] = s[t];
    }
}

// Quad mean value coordinates (their QMVC3D::computeCoordinates: n = 4 samples per side, as in
// the paper). A triquad cage: tris (T, 3), quads (Q, 4) -> out (N, V).
void peer_qmvc(const double *cage, long nv, const long *tris, long nt, const long *quads, long nq,
               const double *pts, long n, double *out) {
    std::vector<point3d> verts = to_points(cage, nv);
    faces_t t3 = to_faces(tris, nt, 3), q4 = to_faces(quads, nq, 4);
    std::vector<double> w;
    for (long i = 0; i < n; ++i) {
        point3d eta(pts[3 * i], pts[3 * i + 1], pts[3 * i + 2]);
        QMVC3D::computeCoordinates<int, double, point3d>(eta, t3, q4, verts, w);
        for (long v = 0; v < nv; ++v) out[i * nv + v] = w[v];
    }
}

}  // extern "C"
