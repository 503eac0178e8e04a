"""Baseline intrinsic-image methods used for comparison (colour Retinex, trivial references)."""

from torchiid.baselines.result import BaselineResult
from torchiid.baselines.retinex import (
    ColorRetinex,
    RetinexResult,
    color_retinex,
    retinex_decomposition,
)
from torchiid.baselines.trivial import reflectance_is_image, shading_is_image

__all__ = [
    "BaselineResult",
    "ColorRetinex",
    "RetinexResult",
    "color_retinex",
    "retinex_decomposition",
    "reflectance_is_image",
    "shading_is_image",
]
