/* torchcage benchmarks/peers: a stand-in for the GNU Scientific Library header that the QMVC
 * authors' point3.h includes for mat33::SVD. The peer driver never calls the SVD, so these
 * declarations only let the header compile without GSL installed; calling one aborts. */
#ifndef TORCHCAGE_PEER_SHIM_GSL_MATRIX_H
#define TORCHCAGE_PEER_SHIM_GSL_MATRIX_H
#include <cstdlib>
#include <cstddef>
struct gsl_matrix { double *data; };
struct gsl_vector { double *data; };
inline gsl_matrix *gsl_matrix_alloc(size_t, size_t) { std::abort(); }
inline gsl_vector *gsl_vector_alloc(size_t) { std::abort(); }
inline void gsl_matrix_set(gsl_matrix *, size_t, size_t, double) { std::abort(); }
inline double gsl_matrix_get(const gsl_matrix *, size_t, size_t) { std::abort(); }
inline double gsl_vector_get(const gsl_vector *, size_t) { std::abort(); }
inline void gsl_matrix_free(gsl_matrix *) { std::abort(); }
inline void gsl_vector_free(gsl_vector *) { std::abort(); }
#endif
