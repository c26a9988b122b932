// torchcage benchmarks/peers: our driver around the LBC authors' solver (Zhang, Deng, Liu, Patane,
// Bouaziz, Hormann, Liu 2014, "Local barycentric coordinates"; https://github.com/bldeng/LBC).
// DataSetup.cpp and LBCSolver.cpp are read from the checkout the user names in TORCHCAGE_PEER_LBC
// and compiled beside this file by benchmarks/peers.py (Eigen 3 headers and OpenMP needed);
// nothing of theirs is in this repository. The mesh is given (torchcage's, so that both solvers
// work on the same one), the boundary points of each cage edge are found as their viewer does.
#include <iostream>
#include <sstream>
#include <vector>

#include <omp.h>

#include "DataSetup.h"
#include "LBCSolver.h"

extern "C" {

int peer_abi_version(void) { return 1; }

// One LBC solve of a 2D polygon cage on a given triangle mesh, run for exactly max_iter ADMM
// iterations (all tolerances 0), one thread, the solver's console output swallowed.
// points (N, 2): mesh vertices; cells (C, 3); ctrl (V,): the mesh vertex of each cage vertex;
// edge_points, edge_offsets (V + 1,): the mesh vertices inside cage edge (i, i + 1) are
// edge_points[edge_offsets[i]:edge_offsets[i + 1]]. scheme: 0 constant, 1 linear, 2 square,
// 3 square root. out (N, V): the coordinates at every mesh vertex.
int peer_lbc2d(const double *points, long n, const long *cells, long nc, const long *ctrl, long nv,
               const long *edge_points, const long *edge_offsets, int scheme, int max_iter, double alpha,
               double penalty, double *out) {
    omp_set_num_threads(1);
    LBC::DenseMatrix sample(2, n);
    for (long i = 0; i < n; ++i) sample(0, i) = points[2 * i], sample(1, i) = points[2 * i + 1];
    LBC::DenseIndexMatrix cell(3, nc);
    for (long c = 0; c < nc; ++c)
        for (int k = 0; k < 3; ++k) cell(k, c) = (int)cells[3 * c + k];
    LBC::IndexVector control(nv);
    for (long v = 0; v < nv; ++v) control(v) = (int)ctrl[v];
    std::vector<LBC::DataSetup::CageBoundaryFacetInfo> facets;
    for (long v = 0; v < nv; ++v) {
        LBC::IndexVector ends(2), inner(edge_offsets[v + 1] - edge_offsets[v]);
        ends << (int)v, (int)((v + 1) % nv);
        for (long k = edge_offsets[v]; k < edge_offsets[v + 1]; ++k) inner(k - edge_offsets[v]) = (int)edge_points[k];
        facets.push_back(LBC::DataSetup::CageBoundaryFacetInfo(ends, inner));
    }
    std::ostringstream sink;
    std::streambuf *saved = std::cout.rdbuf(sink.rdbuf());
    LBC::DataSetup ds(sample, control, cell, facets, static_cast<LBC::DataSetup::WeightingScheme>(scheme));
    LBC::Param param;
    param.max_iterations = max_iter;
    param.relaxation_alpha = alpha;
    param.penalty_weight = penalty;
    param.rel_primal_eps = param.rel_dual_eps = param.abs_eps = 0.0;  // run all max_iter iterations
    param.convergence_check_frequency = 10;
    param.output_frequency_ratio = 1000000;
    param.use_timer = false;
    LBC::LBCSolver solver(param, ds);
    solver.solve();
    LBC::DenseMatrix z = ds.get_full_coordinate_values(solver.get_coordinates());
    std::cout.rdbuf(saved);
    if (z.rows() != n || z.cols() != nv) return -1;
    for (long i = 0; i < n; ++i)
        for (long v = 0; v < nv; ++v) out[i * nv + v] = z(i, v);
    return 0;
}

}  // extern "C"
