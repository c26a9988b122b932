"""The coordinate modules: thin ``nn.Module`` wrappers around precomputed weights."""

from .base import CageModule
from .mean_value import MeanValueCoordinates

__all__ = ["CageModule", "MeanValueCoordinates"]
