"""Validation of decoded pixels: shape, size, channel count, pixel type and finite values.

A file that decodes but cannot be an image for the method raises
:class:`~torchiid.core.exceptions.ImageError` with a one-line message naming the file and the
problem: zero size, smaller than ``min_side`` pixels, an unsupported channel count or pixel
type, NaN / infinity, or negative float values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torchiid.io.bitdepth import bit_depth
from torchiid.io.files import fail

__all__ = ["check_non_negative", "check_pixels"]


def check_pixels(
    path: Path, arr: np.ndarray, orientation: int, min_side: int
) -> tuple[int, int, int, int]:
    """Check a decoded image array; return ``(H, W, channels, bit depth)`` of the upright image.

    Raises:
        ImageError: the array is not 2-D, has zero size or a channel count other than 1-4,
            an unsupported pixel type, NaN or infinite values, or a side below ``min_side``.
    """
    if arr.ndim not in (2, 3):
        raise fail(path, f"has {arr.ndim} dimensions; expected a 2-D image (H, W[, C])")
    h, w = arr.shape[:2]
    if orientation >= 5:
        h, w = w, h
    c = arr.shape[2] if arr.ndim == 3 else 1
    if h == 0 or w == 0:
        raise fail(path, "has zero size")
    if c not in (1, 2, 3, 4):
        raise fail(path, f"has {c} channels; expected 1 (gray), 3 (RGB) or 4 (RGBA)")
    depth = bit_depth(path, arr.dtype)
    if depth == 32 and not np.isfinite(arr).all():
        raise fail(path, f"contains {int((~np.isfinite(arr)).sum())} NaN or infinite values")
    if min(h, w) < min_side:
        raise fail(path, f"is {w}x{h} px; at least {min_side} px per side is needed")
    return h, w, c, depth


def check_non_negative(path: Path, image: np.ndarray) -> None:
    """Raise if a float image has negative values (intensities are >= 0)."""
    if float(image.min()) < 0:
        raise fail(path, "has negative values; expected intensities >= 0")
