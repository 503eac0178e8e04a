"""Bit depth: 8- and 16-bit codes and float values as linear RGB.

Integer files are scaled by 255 or 65535 to ``[0, 1]``; they are sRGB-encoded unless the
caller says they are linear, and are decoded through a lookup table of the exact
IEC 61966-2-1 curve (:func:`~torchiid.core.colour.decode_lut`). Float files are linear and
taken as they are.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from torchiid.core.colour import decode_lut
from torchiid.io.files import fail
from torchiid.io.orientation import orient

__all__ = ["alpha_threshold", "bit_depth", "linear_rgb"]


def bit_depth(path: Path, dtype: np.dtype) -> int:
    """8, 16 or 32 (float, including half-float OpenEXR) for a file's pixel type.

    Raises:
        ImageError: the pixel type is neither uint8, uint16 nor float.
    """
    if dtype == np.uint8:
        return 8
    if dtype == np.uint16:
        return 16
    if dtype.kind == "f":
        return 32
    raise fail(path, f"has pixel type {dtype}; expected uint8, uint16 or float")


def alpha_threshold(dtype: np.dtype) -> float:
    """The value an alpha (or mask) code must exceed to be inside: half the full scale.

    For unsigned integer codes ``code > max / 2`` is exactly ``code / max > 0.5``.
    """
    return np.iinfo(dtype).max / 2 if dtype.kind == "u" else 0.5


def linear_rgb(
    planes: list[np.ndarray], depth: int, linear: bool, orientation: int, size: tuple[int, int]
) -> np.ndarray:
    """``(3, H, W)`` float32 linear RGB of one (gray) or three colour planes, upright.

    Args:
        planes: ``(h, w)`` planes in RGB order as stored (before orientation).
        depth: :func:`bit_depth`.
        linear: the integer codes are linear (no sRGB decoding).
        orientation: the EXIF orientation to apply (:func:`~torchiid.io.orientation.orient`).
        size: ``(H, W)`` of the upright picture.
    """
    out = np.empty((3, *size), np.float32)
    for i, plane in enumerate(planes):
        plane = orient(plane, orientation)
        if depth == 32:
            np.copyto(out[i], plane, casting="same_kind")
        elif depth == 8:
            cv2.LUT(np.ascontiguousarray(plane), decode_lut(8, linear), dst=out[i])
        else:
            np.take(decode_lut(16, linear), plane, out=out[i], mode="clip")
    if len(planes) == 1:  # gray: the same values in R, G and B
        out[1] = out[0]
        out[2] = out[0]
    return out
