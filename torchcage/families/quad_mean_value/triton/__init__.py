"""Triton kernel of quad mean value coordinates."""
