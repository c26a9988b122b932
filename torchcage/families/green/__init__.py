"""Green coordinates (3D triangle cages, 2D polygons) and their derivatives: ``api``, ``module``
(:class:`GreenCoordinates`), ``ops`` (autograd Function), ``dispatch``, the torch kernels
``kernel3d`` / ``kernel2d``, the native glue ``native3d`` / ``derivatives3d_native``, the exterior
extension, the stretch factors and the deformation, and ``triton/``."""
