"""Custom autograd Functions that apply torchcage's analytic derivatives (private: the public
functions route through them when a graph is recorded)."""

from .mean_value import MeanValueFunction, MeanValueGradFunction, MeanValueHessFunction, mean_value_function

__all__ = ["MeanValueFunction", "MeanValueGradFunction", "MeanValueHessFunction", "mean_value_function"]
