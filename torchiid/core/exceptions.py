"""Typed exceptions raised by torchiid.

Every error a user can cause (bad file, bad tensor, bad parameter) is a subclass of
:class:`TorchiidError`, so a caller can catch one type; the CLI turns it into a one-line
message and a non-zero exit status.
"""

from __future__ import annotations

__all__ = [
    "TorchiidError",
    "ImageError",
    "ShapeError",
    "ParameterError",
    "ModelError",
    "ConvergenceWarning",
]


class TorchiidError(ValueError):
    """Base class of every user-facing torchiid error."""


class ImageError(TorchiidError):
    """An image file or tensor cannot be used (unreadable, empty, too small, NaN, ...)."""


class ShapeError(TorchiidError):
    """A tensor has the wrong shape, dtype or device for the operation."""


class ParameterError(TorchiidError):
    """A parameter value or parameter file is invalid."""


class ModelError(TorchiidError):
    """A backbone model (weights or exported ONNX file) is missing or corrupt."""


class ConvergenceWarning(UserWarning):
    """An iterative solver stopped before reaching its tolerance."""
