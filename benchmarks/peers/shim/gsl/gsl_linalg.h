/* torchcage benchmarks/peers: stand-in (see gsl_matrix.h); never called by the peer driver. */
#ifndef TORCHCAGE_PEER_SHIM_GSL_LINALG_H
#define TORCHCAGE_PEER_SHIM_GSL_LINALG_H
#include "gsl_matrix.h"
inline int gsl_linalg_SV_decomp(gsl_matrix *, gsl_matrix *, gsl_vector *, gsl_vector *) { std::abort(); }
#endif
