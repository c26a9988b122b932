"""Solvers behind the coordinates: domain meshing and the LBC ADMM solver."""
