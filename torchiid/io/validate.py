"""Validation of decoded pixels: shape, size, channel count, pixel type and finite values.

A file that decodes but cannot be an image for the method raises
:class:`~torchiid.core.exceptions.ImageError` with a one-line message naming the file and the
problem: zero size, smaller than ``min_side`` pixels, an unsupported channel count or pixel
type, NaN / infinity, or negative float values that are more than noise around 0.

Negative values in a float file. Intensities are ``>= 0``, but renderers' reconstruction
filters ring below 0 beside bright edges, denoisers leave small negatives, and raw merges whose
black level is subtracted scatter dark pixels around 0. Such values are few or shallow, and
:func:`clip_negatives` sets them to 0 (the nearest intensity) and says how many it set. Many
deep ones (a difference image, normals, log values) are a signed encoding that the
decomposition cannot take: the file is refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torchiid.io.bitdepth import bit_depth
from torchiid.io.files import fail

__all__ = ["NEGATIVE_DEPTH", "NEGATIVE_SHARE", "check_pixels", "clip_negatives"]

#: Negative values are set to 0 when at most this share of the values is negative ...
NEGATIVE_SHARE = 0.01
#: ... or when none is deeper than this fraction of the image's bright level (its 99th
#: percentile): noise around 0, however many pixels it touches.
NEGATIVE_DEPTH = 0.01


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
        if arr.ndim == 3 and arr.shape[0] in (1, 3, 4):  # a (C, H, W) array, as torch keeps it
            raise fail(
                path,
                f"holds an array of shape {tuple(arr.shape)}; expected (H, W) or (H, W, 3), "
                "channels last (np.moveaxis(a, 0, -1) turns a (C, H, W) array into one)",
            )
        raise fail(path, f"has {c} channels; expected 1 (gray), 3 (RGB) or 4 (RGBA)")
    depth = bit_depth(path, arr.dtype)
    if depth == 32 and not np.isfinite(arr).all():
        raise fail(path, f"contains {int((~np.isfinite(arr)).sum())} NaN or infinite values")
    if min(h, w) < min_side:
        raise fail(path, f"is {w}x{h} px; at least {min_side} px per side is needed")
    return h, w, c, depth


def clip_negatives(path: Path, image: np.ndarray) -> tuple[int, float]:
    """Set a float image's stray negative values to 0, in place (see the module notes).

    Returns:
        ``(count, lowest)``: how many values were set to 0 and the most negative of them
        (``(0, 0.0)`` when none was negative).

    Raises:
        ImageError: more than :data:`NEGATIVE_SHARE` of the values are negative and the
            deepest is below ``−NEGATIVE_DEPTH`` times the 99th percentile.
    """
    lowest = float(image.min())
    if not lowest < 0:
        return 0, 0.0
    count = int(np.count_nonzero(image < 0))
    share = count / image.size
    if share > NEGATIVE_SHARE:
        level = float(np.quantile(image, 0.99))
        if not -lowest <= NEGATIVE_DEPTH * level:
            raise fail(
                path,
                f"has negative values ({share:.1%} of its values, down to {lowest:.4g}); expected "
                "intensities >= 0, not a signed image such as a difference, normals or logs",
            )
    np.maximum(image, 0, out=image)
    return count, lowest
