"""EXIF orientation: the picture as viewers show it.

The EXIF Orientation tag (values 1-8) of JPEG, PNG, TIFF and WebP files is applied by the
readers, so an array is the picture upright, the same result as Pillow's
``ImageOps.exif_transpose``.
"""

from __future__ import annotations

import numpy as np
from PIL import Image

__all__ = ["exif_orientation", "orient"]


def exif_orientation(payload: bytes | None) -> int:
    """The Orientation (0x0112) of an EXIF block parsed by Pillow; 1 if absent or unreadable."""
    if not payload:
        return 1
    try:
        exif = Image.Exif()
        exif.load(payload)
        value = exif.get(0x0112)
    except Exception:  # noqa: BLE001 - any broken EXIF block means "no orientation"
        return 1
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


def orient(arr: np.ndarray, orientation: int) -> np.ndarray:
    """A view of ``arr`` ``(H, W[, C])`` turned as Pillow's ``ImageOps.exif_transpose`` does."""
    if orientation == 2:  # FLIP_LEFT_RIGHT
        return arr[:, ::-1]
    if orientation == 3:  # ROTATE_180
        return arr[::-1, ::-1]
    if orientation == 4:  # FLIP_TOP_BOTTOM
        return arr[::-1]
    if orientation == 5:  # TRANSPOSE
        return arr.swapaxes(0, 1)
    if orientation == 6:  # ROTATE_270 (90 degrees clockwise)
        return np.rot90(arr, -1)
    if orientation == 7:  # TRANSVERSE
        return arr.swapaxes(0, 1)[::-1, ::-1]
    if orientation == 8:  # ROTATE_90 (90 degrees counter-clockwise)
        return np.rot90(arr)
    return arr
