"""The one image loader of torchiid, and where its savers are found.

Reading (:func:`load_image`, :func:`load_mask`, :func:`~torchiid.io.exr.read_exr`):

* 8-bit and 16-bit PNG / JPEG / TIFF / BMP / WebP files are decoded with OpenCV's
  ``IMREAD_UNCHANGED`` so no bit depth is lost (:mod:`torchiid.io.decode`); values are scaled by
  255 or 65535 to ``[0, 1]`` (:mod:`torchiid.io.bitdepth`).
* The EXIF Orientation tag (values 1-8) of JPEG, PNG, TIFF and WebP files is applied, so the
  array is the picture as viewers show it (the same result as Pillow's
  ``ImageOps.exif_transpose``, :mod:`torchiid.io.orientation`); :attr:`LoadedImage.orientation`
  tells which value the file holds.
* Float files (32-bit float TIFF, OpenEXR ``.exr`` with channels ``Y`` or ``R``, ``G``, ``B``
  and optionally ``A``, half or float; ``.npy`` arrays of shape ``(H, W)``, ``(H, W, 3)`` or
  ``(H, W, 4)``) are taken as they are.
* Colour encoding: integer files are sRGB-encoded unless ``linear=True`` (the CLI's
  ``--linear``) and are decoded through a lookup table of the exact IEC 61966-2-1 curve; float
  files are linear. The returned image is always **linear RGB**.
* Gray files are promoted to RGB; an alpha channel is, by default, used as a mask
  (``alpha > 0.5`` is inside) — pass ``alpha="error"`` to reject it or ``alpha="ignore"``.
* Damaged files are rejected, never returned with filler (:mod:`torchiid.io.damage`): the
  structure of JPEG, PNG, WebP and TIFF files is checked before decoding, libjpeg's reports of
  damaged data reject a JPEG, and OpenEXR pixel data must decode.
* What the C decoders print to stderr is collected and logged (``torchiid -v`` shows it),
  not left on the terminal beside torchiid's one-line error.
* Bad files raise :class:`~torchiid.core.exceptions.ImageError` with a one-line message naming
  the file and the problem: missing, unreadable, empty, not an image, truncated or corrupt,
  zero size, smaller than ``min_side`` pixels, containing NaN / infinity, or holding signed
  values (:mod:`torchiid.io.validate`). A float file's stray negative values (a
  reconstruction filter's ringing, noise around a subtracted black level) are set to 0 with an
  :class:`~torchiid.core.exceptions.InputWarning` that says how many.

Writing (:func:`~torchiid.io.write.save_image`, :func:`~torchiid.io.write.save_uint8`,
:func:`~torchiid.io.write.save_codes`, :func:`~torchiid.io.write.save_encoded`) is atomic and
lives in :mod:`torchiid.io.write`; the savers, :func:`~torchiid.io.exr.read_exr` and the sRGB
curves stay importable from here.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from torchiid.core.check import MIN_SIDE
from torchiid.core.colour import linear_to_srgb as linear_to_srgb
from torchiid.core.colour import srgb_to_linear as srgb_to_linear
from torchiid.core.exceptions import InputWarning
from torchiid.io.bitdepth import alpha_threshold, linear_rgb
from torchiid.io.decode import read_array, rgb_planes
from torchiid.io.exr import read_exr as read_exr
from torchiid.io.files import fail
from torchiid.io.orientation import orient
from torchiid.io.validate import check_pixels, clip_negatives
from torchiid.io.write import Encoding as Encoding
from torchiid.io.write import encode_codes as encode_codes
from torchiid.io.write import save_codes as save_codes
from torchiid.io.write import save_encoded as save_encoded
from torchiid.io.write import save_image as save_image
from torchiid.io.write import save_uint8 as save_uint8

__all__ = ["LoadedImage", "load_image", "load_mask"]


@dataclass(frozen=True)
class LoadedImage:
    """An image read from disk.

    Attributes:
        image: ``(3, H, W)`` float32 **linear** RGB in ``[0, 1]`` (float files may exceed 1),
            upright: the EXIF orientation is already applied.
        mask: ``(1, H, W)`` bool from the alpha channel, or ``None``.
        path: the file it came from.
        bit_depth: 8, 16 or 32 (float, including half-float OpenEXR).
        linear_file: whether the file's values are taken as linear (no sRGB decoding).
        orientation: the EXIF Orientation value (1-8) applied; 1 when the file has none.
        negatives: how many values of a float file were negative and are set to 0 in
            :attr:`image` (:func:`~torchiid.io.validate.clip_negatives`).
        lowest: the most negative of them (0 when there were none).
    """

    image: torch.Tensor
    mask: torch.Tensor | None
    path: Path
    bit_depth: int
    linear_file: bool
    orientation: int = 1
    negatives: int = 0
    lowest: float = 0.0

    def negatives_note(self) -> str | None:
        """A one-line note saying how many negative values were set to 0, or ``None``."""
        if not self.negatives:
            return None
        values = "value" if self.negatives == 1 else "values"
        return (
            f"{self.path}: {self.negatives} negative {values} (down to {self.lowest:.4g}) set to 0"
        )


def load_image(
    path: str | os.PathLike,
    linear: bool = False,
    alpha: Literal["mask", "error", "ignore"] = "mask",
    min_side: int = MIN_SIDE,
) -> LoadedImage:
    """Read an image file as upright linear RGB.

    Args:
        path: the file (PNG, JPEG, TIFF, BMP, WebP, OpenEXR, or ``.npy``).
        linear: the integer file holds linear values (do not decode sRGB).
        alpha: what an alpha channel means: ``"mask"`` (alpha > 0.5 is inside, the default),
            ``"error"`` (reject the file) or ``"ignore"``.
        min_side: smallest allowed height and width (the method's patches are 60 px).

    Returns:
        :class:`LoadedImage` with a ``(3, H, W)`` float32 linear image, turned upright by the
        file's EXIF orientation.

    Raises:
        ImageError: the file is missing, unreadable, empty, not an image, truncated or
            corrupt, zero-size, too small, has an unsupported channel count, contains
            NaN/infinity, or (a float file) holds signed values rather than intensities.

    Warns:
        InputWarning: a float file's few or shallow negative values are set to 0
            (:func:`~torchiid.io.validate.clip_negatives`; counted in
            :attr:`LoadedImage.negatives`).
    """
    path = Path(path)
    decoded = read_array(path)
    orientation = decoded.orientation
    h, w, c, depth = check_pixels(path, decoded.arr, orientation, min_side)
    planes = rgb_planes(decoded)
    mask = None
    if c in (2, 4):
        mask = _alpha_mask(path, planes.pop(), orientation, alpha)
    is_linear = linear or depth == 32
    out = linear_rgb(planes, depth, is_linear, orientation, (h, w))
    negatives, lowest = clip_negatives(path, out) if depth == 32 else (0, 0.0)
    loaded = LoadedImage(
        image=torch.from_numpy(out),
        mask=mask,
        path=path,
        bit_depth=depth,
        linear_file=is_linear,
        orientation=orientation,
        negatives=negatives,
        lowest=lowest,
    )
    note = loaded.negatives_note()
    if note is not None:
        warnings.warn(note, InputWarning, stacklevel=2)
    return loaded


def _alpha_mask(
    path: Path, alpha_plane: np.ndarray, orientation: int, alpha: str
) -> torch.Tensor | None:
    """The ``(1, H, W)`` mask of an alpha plane as ``alpha`` asks (``None``: ignored)."""
    if alpha == "error":
        raise fail(path, "has an alpha channel; remove it or pass alpha='mask'")
    if alpha != "mask":
        return None
    inside = orient(alpha_plane, orientation) > alpha_threshold(alpha_plane.dtype)
    mask = torch.from_numpy(np.ascontiguousarray(inside))[None]
    if not bool(mask.any()):
        raise fail(path, "alpha channel is fully transparent (empty mask)")
    return mask


def load_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> torch.Tensor:
    """Read a mask file: nonzero (or alpha > 0.5 where present) is inside.

    Args:
        path: an image file; colour masks count a pixel as inside if any channel is nonzero.
            The EXIF orientation is applied as for :func:`load_image`.
        shape: expected ``(H, W)``; a mismatch raises :class:`ImageError`.

    Returns:
        ``(1, H, W)`` bool tensor.

    Raises:
        ImageError: the file cannot be read (see :func:`load_image`), its size differs from
            ``shape``, or no pixel is inside.
    """
    path = Path(path)
    decoded = read_array(path)
    arr = decoded.arr
    if arr.ndim < 2:
        raise fail(path, f"has {arr.ndim} dimensions; expected a 2-D image (H, W[, C])")
    if arr.ndim == 3 and arr.shape[2] in (2, 4):
        inside = arr[..., -1] > alpha_threshold(arr.dtype)
    else:
        inside = (arr.reshape(arr.shape[0], arr.shape[1], -1) > 0).any(axis=2)
    inside = orient(inside, decoded.orientation)
    if shape is not None and inside.shape != tuple(shape):
        raise fail(
            path,
            f"mask is {inside.shape[1]}x{inside.shape[0]} px but the image is "
            f"{shape[1]}x{shape[0]} px",
        )
    if not inside.any():
        raise fail(path, "mask is empty (no pixel inside)")
    return torch.from_numpy(np.ascontiguousarray(inside))[None]
