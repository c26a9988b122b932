"""Triton kernel of 3D Green coordinates."""
