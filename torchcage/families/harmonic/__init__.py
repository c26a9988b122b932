"""Harmonic coordinates, solved on a mesh of the cage interior (:mod:`torchcage.solvers`): ``api``
and ``module``."""
