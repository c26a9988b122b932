"""Triton kernels of mean value coordinates and their derivatives (triton is imported here only,
lazily by the callers)."""
