"""Mean value coordinates (3D triangle cages, 2D polygons) and their analytic derivatives: ``api``
(the public functions), ``module`` (:class:`MeanValueCoordinates`), ``ops`` (autograd Functions and
the ``torch.ops.torchcage`` custom ops), ``dispatch`` (the kernel chosen, chunk by chunk), the torch
kernels ``kernel3d`` / ``kernel2d``, the native glue ``native3d`` / ``native2d`` / ``vjp3d_native`` /
``derivatives_native``, and ``triton/`` (the Triton kernels)."""
