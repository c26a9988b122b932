"""Bounded biharmonic weights, solved on a mesh of the cage interior: ``api`` and ``module``."""
