// torchcage benchmarks/peers: our driver around CageModeler's Green coordinates for triquad cages
// (QGC of Thiery and Boubekeur 2022, as implemented in https://github.com/DanStroeter/CageModeler,
// cagedeformations/src/GreenCoordinates.cpp). Their source is read from the checkout the user names
// in TORCHCAGE_PEER_CAGEMODELER and compiled beside this file by benchmarks/peers.py (Eigen 3
// headers needed); nothing of theirs is in this repository.
#include <vector>

#include <Eigen/Dense>

#include <cagedeformations/GreenCoordinates.h>

extern "C" {

int peer_abi_version(void) { return 1; }

// Quad Green coordinates, their calculateGreenCoordinatesTriQuad (n = 2, fixed in their code), one
// thread. A triquad cage: tris (T, 3), quads (Q, 4); points (N, 3) -> phi (N, V) and psi
// (N, T + 4 Q): the T triangle columns multiply unit outward normals, then for quad q and corner k
// column T + 4 q + k multiplies the corner normal (q_{k+1} - q_k) x (q_{k+3} - q_k).
void peer_qgc(const double *cage, long nv, const long *tris, long nt, const long *quads, long nq,
              const double *pts, long n, double *phi, double *psi) {
    Eigen::MatrixXd C(nv, 3), X(n, 3), P;
    for (long i = 0; i < nv; ++i)
        for (int k = 0; k < 3; ++k) C(i, k) = cage[3 * i + k];
    for (long i = 0; i < n; ++i)
        for (int k = 0; k < 3; ++k) X(i, k) = pts[3 * i + k];
    Eigen::MatrixXi CF(nt + nq, 4);  // their layout: a triangle has -1 as its fourth index
    for (long f = 0; f < nt; ++f) CF.row(f) << (int)tris[3 * f], (int)tris[3 * f + 1], (int)tris[3 * f + 2], -1;
    for (long f = 0; f < nq; ++f)
        CF.row(nt + f) << (int)quads[4 * f], (int)quads[4 * f + 1], (int)quads[4 * f + 2], (int)quads[4 * f + 3];
    std::vector<double> psi_tri;
    std::vector<Eigen::Vector4d> psi_quad;
    calculateGreenCoordinatesTriQuad(C, CF, X, P, psi_tri, psi_quad);
    long m = nt + 4 * nq;
    for (long i = 0; i < n; ++i) {
        for (long v = 0; v < nv; ++v) phi[i * nv + v] = P(v, i);
        for (long t = 0; t < nt; ++t) psi[i * m + t] = psi_tri[i * nt + t];
        for (long q = 0; q < nq; ++q)
            for (int k = 0; k < 4; ++k) psi[i * m + nt + 4 * q + k] = psi_quad[i * nq + q](k);
    }
}

}  // extern "C"
