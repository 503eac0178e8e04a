"""The one image loader and saver of torchiid.

Reading (:func:`load_image`):

* 8-bit and 16-bit PNG / JPEG / TIFF / BMP / WebP files are read with OpenCV's
  ``IMREAD_UNCHANGED`` so no bit depth is lost, then scaled by 255 or 65535 to ``[0, 1]``.
* Float files (32-bit float TIFF, ``.npy`` arrays of shape ``(H, W)``, ``(H, W, 3)`` or
  ``(H, W, 4)``) are taken as they are.
* Colour encoding: integer files are sRGB-encoded unless ``linear=True`` (the CLI's
  ``--linear``); float files are linear. The returned image is always **linear RGB**.
* Gray files are promoted to RGB; an alpha channel is, by default, used as a mask
  (``alpha > 0.5`` is inside) — pass ``alpha="error"`` to reject it or ``alpha="ignore"``.
* Bad files raise :class:`~torchiid.core.exceptions.ImageError` with a one-line message naming
  the file and the problem: missing, unreadable, empty, not an image, zero size, smaller than
  ``min_side`` pixels, or containing NaN / infinity.

Writing (:func:`save_image`) is atomic: the data go to a temporary file in the target folder,
which is renamed over the target only when complete, so an output is never half-written.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import kornia
import numpy as np
import torch

from torchiid.core.check import MIN_SIDE
from torchiid.core.exceptions import ImageError

__all__ = [
    "LoadedImage",
    "load_image",
    "load_mask",
    "save_image",
    "save_uint8",
    "srgb_to_linear",
    "linear_to_srgb",
]

Encoding = Literal["srgb8", "srgb16", "linear16", "npy"]


@dataclass(frozen=True)
class LoadedImage:
    """An image read from disk.

    Attributes:
        image: ``(3, H, W)`` float32 **linear** RGB in ``[0, 1]`` (float files may exceed 1).
        mask: ``(1, H, W)`` bool from the alpha channel, or ``None``.
        path: the file it came from.
        bit_depth: 8, 16 or 32 (float).
        linear_file: whether the file's values were taken as linear (no sRGB decoding).
    """

    image: torch.Tensor
    mask: torch.Tensor | None
    path: Path
    bit_depth: int
    linear_file: bool


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """Decode sRGB values in ``[0, 1]`` to linear RGB (the exact IEC 61966-2-1 curve).

    Shape: any; ``(B, 3, H, W)`` or ``(3, H, W)`` are typical.
    """
    return (
        kornia.color.rgb_to_linear_rgb(x.clamp(0, 1))
        if x.dim() >= 3 and x.shape[-3] == 3
        else torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0) + 0.055) / 1.055) ** 2.4)
    )


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Encode linear RGB to sRGB in ``[0, 1]`` (values are clipped to ``[0, 1]`` first)."""
    x = x.clamp(0, 1)
    if x.dim() >= 3 and x.shape[-3] == 3:
        return kornia.color.linear_rgb_to_rgb(x).clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1 / 2.4) - 0.055).clamp(0, 1)


def _fail(path: Path, problem: str) -> ImageError:
    return ImageError(f"{path}: {problem}")


def _read_array(path: Path) -> np.ndarray:
    if not path.exists():
        raise _fail(path, "no such file")
    if path.is_dir():
        raise _fail(path, "is a directory, not an image file")
    if not os.access(path, os.R_OK):
        raise _fail(path, "cannot be read (permission denied)")
    if path.stat().st_size == 0:
        raise _fail(path, "is empty (0 bytes)")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise _fail(path, f"is not a readable .npy array ({exc})") from None
        if arr.dtype.kind not in "fiu":
            raise _fail(path, f"holds a {arr.dtype} array, expected numbers")
        return arr
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise _fail(path, "is not an image OpenCV can decode (corrupt or unsupported format)")
    if arr.ndim == 3 and arr.shape[2] in (3, 4):  # OpenCV gives BGR(A)
        arr = arr[..., [2, 1, 0, 3][: arr.shape[2]]]
    return arr


def load_image(
    path: str | os.PathLike,
    linear: bool = False,
    alpha: Literal["mask", "error", "ignore"] = "mask",
    min_side: int = MIN_SIDE,
) -> LoadedImage:
    """Read an image file as linear RGB.

    Args:
        path: the file (PNG, JPEG, TIFF, BMP, WebP, or ``.npy``).
        linear: the integer file holds linear values (do not decode sRGB).
        alpha: what an alpha channel means: ``"mask"`` (alpha > 0.5 is inside, the default),
            ``"error"`` (reject the file) or ``"ignore"``.
        min_side: smallest allowed height and width (the method's patches are 60 px).

    Returns:
        :class:`LoadedImage` with a ``(3, H, W)`` float32 linear image.

    Raises:
        ImageError: the file is missing, unreadable, empty, not an image, zero-size, too
            small, has an unsupported channel count, or contains NaN/infinity.
    """
    path = Path(path)
    arr = _read_array(path)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise _fail(path, f"has {arr.ndim} dimensions; expected a 2-D image (H, W[, C])")
    h, w, c = arr.shape
    if h == 0 or w == 0:
        raise _fail(path, "has zero size")
    if c not in (1, 2, 3, 4):
        raise _fail(path, f"has {c} channels; expected 1 (gray), 3 (RGB) or 4 (RGBA)")
    if arr.dtype == np.uint8:
        depth, scale = 8, 255.0
    elif arr.dtype == np.uint16:
        depth, scale = 16, 65535.0
    elif arr.dtype.kind == "f":
        depth, scale = 32, 1.0
    else:
        raise _fail(path, f"has pixel type {arr.dtype}; expected uint8, uint16 or float")
    data = arr.astype(np.float32) / np.float32(scale)
    if not np.isfinite(data).all():
        raise _fail(path, f"contains {int((~np.isfinite(data)).sum())} NaN or infinite values")
    if min(h, w) < min_side:
        raise _fail(path, f"is {w}x{h} px; at least {min_side} px per side is needed")
    mask = None
    if c in (2, 4):
        if alpha == "error":
            raise _fail(path, "has an alpha channel; remove it or pass alpha='mask'")
        if alpha == "mask":
            mask = torch.from_numpy(np.ascontiguousarray(data[..., -1] > 0.5))[None]
            if not bool(mask.any()):
                raise _fail(path, "alpha channel is fully transparent (empty mask)")
        data = data[..., :-1]
    if data.shape[2] == 1:
        data = np.repeat(data, 3, axis=2)
    img = torch.from_numpy(np.ascontiguousarray(data)).permute(2, 0, 1).contiguous()
    is_linear = linear or depth == 32
    if not is_linear:
        img = srgb_to_linear(img)
    if bool((img < 0).any()):
        raise _fail(path, "has negative values; expected intensities >= 0")
    return LoadedImage(image=img, mask=mask, path=path, bit_depth=depth, linear_file=is_linear)


def load_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> torch.Tensor:
    """Read a mask file: nonzero (or alpha > 0.5 where present) is inside.

    Args:
        path: an image file; colour masks count a pixel as inside if any channel is nonzero.
        shape: expected ``(H, W)``; a mismatch raises :class:`ImageError`.

    Returns:
        ``(1, H, W)`` bool tensor.
    """
    path = Path(path)
    arr = _read_array(path)
    if arr.ndim == 3 and arr.shape[2] in (2, 4):
        inside = arr[..., -1] > (np.iinfo(arr.dtype).max / 2 if arr.dtype.kind == "u" else 0.5)
    else:
        inside = (arr.reshape(arr.shape[0], arr.shape[1], -1) > 0).any(axis=2)
    if shape is not None and inside.shape != tuple(shape):
        raise _fail(
            path,
            f"mask is {inside.shape[1]}x{inside.shape[0]} px but the image is "
            f"{shape[1]}x{shape[0]} px",
        )
    if not inside.any():
        raise _fail(path, "mask is empty (no pixel inside)")
    return torch.from_numpy(np.ascontiguousarray(inside))[None]


def _to_hwc(x: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu", torch.float32)
        if x.dim() == 4:
            if x.shape[0] != 1:
                raise ImageError(f"save_image takes one image, got a batch of {x.shape[0]}")
            x = x[0]
        if x.dim() == 3:
            x = x.permute(1, 2, 0)
        x = x.numpy()
    x = np.asarray(x, dtype=np.float32)
    if x.ndim == 3 and x.shape[2] == 1:
        x = x[..., 0]
    return x


def save_image(
    path: str | os.PathLike,
    image: torch.Tensor | np.ndarray,
    encoding: Encoding = "srgb8",
) -> Path:
    """Write a **linear** image atomically.

    Args:
        path: target file. ``.png`` (or ``.tif``) for the integer encodings, ``.npy`` for float.
        image: linear values, ``(3, H, W)``/``(1, 3, H, W)``/``(1, H, W)`` tensor or
            ``(H, W[, 3])`` array.
        encoding: ``"srgb8"`` (viewable 8-bit sRGB PNG, values clipped to [0, 1]),
            ``"srgb16"`` (16-bit sRGB), ``"linear16"`` (16-bit linear, clipped to [0, 1]) or
            ``"npy"`` (float32 linear, unclipped, channel-last).

    Returns:
        The written path.
    """
    path = Path(path)
    arr = _to_hwc(image)
    if encoding == "npy":
        payload = arr
    else:
        lin = np.clip(arr, 0, 1)
        if encoding in ("srgb8", "srgb16"):
            lin = (
                linear_to_srgb(torch.from_numpy(lin)).numpy()
                if lin.ndim == 2
                else linear_to_srgb(torch.from_numpy(lin).permute(2, 0, 1)).permute(1, 2, 0).numpy()
            )
        if encoding == "srgb8":
            payload = np.round(lin * 255).astype(np.uint8)
        elif encoding in ("srgb16", "linear16"):
            payload = np.round(lin * 65535).astype(np.uint16)
        else:
            raise ValueError(f"unknown encoding {encoding!r}; use srgb8, srgb16, linear16 or npy")
        if payload.ndim == 3:
            payload = np.ascontiguousarray(payload[..., ::-1])  # RGB -> BGR for OpenCV
    _atomic_write(path, payload, npy=(encoding == "npy"))
    return path


def save_uint8(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` or ``(H, W)`` uint8 picture (already sRGB) atomically as is."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim not in (2, 3):
        raise ImageError(
            f"save_uint8 takes an (H, W[, 3]) uint8 array, got {rgb.dtype} {rgb.shape}"
        )
    payload = np.ascontiguousarray(rgb[..., ::-1]) if rgb.ndim == 3 else rgb
    path = Path(path)
    _atomic_write(path, payload)
    return path


def _atomic_write(path: Path, payload: np.ndarray, npy: bool = False) -> None:
    """Write to a temporary file in the target folder, then rename it over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        if npy:
            with open(tmp, "wb") as fh:
                np.save(fh, payload)
        else:
            ok, buf = cv2.imencode(path.suffix or ".png", payload)
            if not ok:
                raise ImageError(f"{path}: OpenCV cannot encode a {path.suffix} file")
            with open(tmp, "wb") as fh:
                fh.write(buf.tobytes())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
