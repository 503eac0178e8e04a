"""The sRGB transfer curve (IEC 61966-2-1), the one implementation of the package.

Every conversion between linear RGB and sRGB in torchiid goes through this module:

- :func:`srgb_to_linear` / :func:`linear_to_srgb` for torch tensors (any shape, any floating
  dtype, differentiable with a finite gradient everywhere, also at 0);
- :func:`linear_to_srgb_np` for numpy arrays (float64 through NumPy's ``power``, for the
  OpenCV-based selective search and the output lookup table);
- lookup tables for integer codes: :func:`decode_lut` (8- or 16-bit file codes -> float32
  linear values) and :func:`srgb8_encode_lut` (16-bit linear codes -> 8-bit sRGB codes).

The curve is the exact piecewise one, not a gamma 2.2 approximation::

    encode: s = 12.92 x                     for x <= 0.0031308
            s = 1.055 x^(1/2.4) - 0.055     otherwise
    decode: x = s / 12.92                   for s <= 0.04045
            x = ((s + 0.055) / 1.055)^2.4   otherwise

Inputs are clipped to ``[0, 1]`` first, in both directions. The torch functions compute the
same expressions, in the same order, as :func:`kornia.color.linear_rgb_to_rgb` and
:func:`kornia.color.rgb_to_linear_rgb` (bit-identical results on ``(*, 3, H, W)`` inputs), but
accept any shape.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

__all__ = [
    "ENCODE_THRESHOLD",
    "DECODE_THRESHOLD",
    "srgb_to_linear",
    "linear_to_srgb",
    "linear_to_srgb_np",
    "decode_lut",
    "srgb8_encode_lut",
]

#: linear values up to this one are encoded by the straight segment ``12.92 x``
ENCODE_THRESHOLD = 0.0031308
#: sRGB values up to this one are decoded by the straight segment ``s / 12.92``
DECODE_THRESHOLD = 0.04045


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """Decode sRGB values to linear RGB (values are clipped to ``[0, 1]`` first).

    Args:
        x: sRGB-encoded values, any shape and floating dtype (``(B, 3, H, W)`` or
            ``(3, H, W)`` are typical).

    Returns:
        Linear values in ``[0, 1]``, same shape and dtype.

    >>> srgb_to_linear(torch.tensor([0.0, 0.5, 1.0, 2.0]))
    tensor([0.0000, 0.2140, 1.0000, 1.0000])
    """
    x = x.clamp(0, 1)
    return torch.where(
        x > DECODE_THRESHOLD,
        torch.pow((x + 0.055).clamp(min=0.0) / 1.055, 2.4),
        x / 12.92,
    )


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Encode linear RGB to sRGB in ``[0, 1]`` (values are clipped to ``[0, 1]`` first).

    The power branch sees its input clamped to the threshold, so the gradient stays finite at 0.

    Args:
        x: linear values, any shape and floating dtype.

    Returns:
        sRGB values in ``[0, 1]``, same shape and dtype.

    >>> linear_to_srgb(torch.tensor([-1.0, 0.0, 0.2140, 1.0, 3.0]))
    tensor([0.0000, 0.0000, 0.5000, 1.0000, 1.0000])
    """
    x = x.clamp(0, 1)
    s = torch.where(
        x > ENCODE_THRESHOLD,
        1.055 * torch.pow(x.clamp(min=ENCODE_THRESHOLD), 1 / 2.4) - 0.055,
        12.92 * x,
    )
    return s.clamp(0, 1)


def linear_to_srgb_np(x: np.ndarray) -> np.ndarray:
    """:func:`linear_to_srgb` for numpy arrays (values are clipped to ``[0, 1]`` first).

    Computed with NumPy's ``power`` in the array's floating dtype (callers pass float64).

    Args:
        x: linear values, any shape.

    Returns:
        sRGB values in ``[0, 1]``, same shape.

    >>> linear_to_srgb_np(np.array([0.0, 0.2140, 1.0, 3.0])).round(4)
    array([0. , 0.5, 1. , 1. ])
    """
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= ENCODE_THRESHOLD, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def decode_lut(depth: int, linear: bool = False) -> np.ndarray:
    """Float32 value of every 8- or 16-bit code: ``code / (2^depth - 1)``, sRGB-decoded.

    The table is computed in float64 with :func:`srgb_to_linear` and rounded once to float32;
    it is cached and read-only.

    Args:
        depth: bits per code, 8 or 16.
        linear: the codes hold linear values (no sRGB decoding, only the scaling).

    Returns:
        ``(2^depth,)`` float32 array indexed by the code.

    >>> lut = decode_lut(8)
    >>> lut.shape, lut.dtype, float(lut[0]), float(lut[255])
    ((256,), dtype('float32'), 0.0, 1.0)
    """
    return _decode_lut(int(depth), bool(linear))


@functools.cache
def _decode_lut(depth: int, linear: bool) -> np.ndarray:
    n = 1 << depth
    lut: np.ndarray
    if linear:
        lut = np.arange(n, dtype=np.float32) / np.float32(n - 1)
    else:
        codes = torch.arange(n, dtype=torch.float64) / (n - 1)
        lut = srgb_to_linear(codes).numpy().astype(np.float32)
    lut.flags.writeable = False
    return lut


@functools.cache
def srgb8_encode_lut() -> np.ndarray:
    """uint8 sRGB code of every 16-bit linear code (65536 entries; cached, read-only).

    Entry ``c`` is ``round(255 · linear_to_srgb_np(c / 65535))``, computed in float64.

    >>> lut = srgb8_encode_lut()
    >>> lut.shape, lut.dtype, int(lut[0]), int(lut[65535])
    ((65536,), dtype('uint8'), 0, 255)
    """
    x = np.arange(65536, dtype=np.float64) / 65535
    lut: np.ndarray = np.clip(np.rint(linear_to_srgb_np(x) * 255), 0, 255).astype(np.uint8)
    lut.flags.writeable = False
    return lut
