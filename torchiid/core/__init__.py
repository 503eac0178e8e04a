"""Shared machinery: exceptions, input checks, the device, the sRGB curve, torch.compile.

The names below load on first use (:mod:`torchiid._lazy`): ``torchiid.core.exceptions`` and
the other light modules import without torch.
"""

from typing import TYPE_CHECKING

from torchiid._lazy import lazy_names

if TYPE_CHECKING:  # what static tools see; at run time: __getattr__
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

_SOURCES = {
    **dict.fromkeys(
        ["check_finite", "check_image", "check_same_batch", "check_shape"], "torchiid.core.check"
    ),
    **dict.fromkeys(["linear_to_srgb", "srgb_to_linear"], "torchiid.core.colour"),
    "resolve_device": "torchiid.core.device",
    **dict.fromkeys(
        [
            "ConvergenceWarning",
            "ImageError",
            "ModelError",
            "ParameterError",
            "ShapeError",
            "TorchiidError",
        ],
        "torchiid.core.exceptions",
    ),
}
__getattr__, __dir__ = lazy_names(__name__, _SOURCES, globals())
