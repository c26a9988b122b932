"""Quad mean value coordinates (triquad cages): ``api``, ``module``, the torch ``kernel``, the native
glue ``native`` and ``triton/``."""
