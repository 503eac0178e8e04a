"""Shared machinery: exceptions, input checks, the device choice and the sRGB curve."""

from torchiid.core.check import check_finite, check_image, check_same_batch, check_shape
from torchiid.core.colour import linear_to_srgb, srgb_to_linear
from torchiid.core.device import resolve_device
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
    "linear_to_srgb",
    "resolve_device",
    "srgb_to_linear",
    "ConvergenceWarning",
    "ImageError",
    "ModelError",
    "ParameterError",
    "ShapeError",
    "TorchiidError",
]
