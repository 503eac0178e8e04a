"""Shared machinery: exceptions and input checks."""

from torchiid.core.check import check_finite, check_image, check_same_batch, check_shape
from torchiid.core.exceptions import (
    ConvergenceWarning,
    ImageError,
    ModelError,
    ParameterError,
    ShapeError,
    TorchiidError,
)

__all__ = [
    "check_finite",
    "check_image",
    "check_same_batch",
    "check_shape",
    "ConvergenceWarning",
    "ImageError",
    "ModelError",
    "ParameterError",
    "ShapeError",
    "TorchiidError",
]
