"""Quad Green coordinates (triquad cages): ``api``, ``module``, the torch ``kernel``, the native glue
``native`` and the deformation with per-corner correction factors."""
