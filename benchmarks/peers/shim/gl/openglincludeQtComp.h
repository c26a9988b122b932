/* torchcage benchmarks/peers: stand-in for the Qt/OpenGL include of the QMVC authors' point3.h
 * (drawing helpers, never called by the peer driver; calling one aborts). */
#ifndef TORCHCAGE_PEER_SHIM_OPENGL_H
#define TORCHCAGE_PEER_SHIM_OPENGL_H
#include <cstdlib>
inline void glVertex3f(float, float, float) { std::abort(); }
inline void glNormal3f(float, float, float) { std::abort(); }
#endif
