"""The coordinate modules: thin ``nn.Module`` wrappers around precomputed weights."""

from .base import CageModule
from .green import GreenCoordinates
from .mean_value import MeanValueCoordinates

__all__ = ["CageModule", "GreenCoordinates", "MeanValueCoordinates"]
