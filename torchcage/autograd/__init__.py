"""Custom autograd Functions that apply torchcage's analytic derivatives of mean value coordinates.

The public functions route through them when a graph is recorded and the native kernel serves
(:func:`torchcage.functional.mean_value_coordinates`); they are public for users who compose
them directly: ``MeanValueFunction.apply(points (N, D), vertices (V, D), faces, chunk_size, backend)``.
Their ``torch.library`` custom ops (``torch.ops.torchcage.*``) register at ``import torchcage``.
"""

from torchcage.families.mean_value.ops import (
    MeanValueFunction,
    MeanValueGradFunction,
    MeanValueHessFunction,
    mean_value_function,
)

__all__ = ["MeanValueFunction", "MeanValueGradFunction", "MeanValueHessFunction", "mean_value_function"]
