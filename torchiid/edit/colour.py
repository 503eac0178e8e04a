"""Colours of the edits: named tints, colour parsing and CIELab of linear RGB."""

from __future__ import annotations

import math
from collections.abc import Sequence

import kornia
import torch

from torchiid.core.exceptions import ParameterError

__all__ = ["COLOURS", "lab_to_linear", "linear_to_lab", "parse_colour"]

#: named tints (sRGB in [0, 1]) accepted by :func:`parse_colour`
COLOURS = {
    "red": (1.0, 0.0, 0.0),
    "green": (0.0, 1.0, 0.0),
    "blue": (0.0, 0.0, 1.0),
    "yellow": (1.0, 1.0, 0.0),
    "cyan": (0.0, 1.0, 1.0),
    "magenta": (1.0, 0.0, 1.0),
    "orange": (1.0, 0.5, 0.0),
    "warm": (1.0, 0.75, 0.5),
    "cool": (0.6, 0.8, 1.0),
    "white": (1.0, 1.0, 1.0),
}


def parse_colour(colour: str | Sequence[float]) -> tuple[float, float, float]:
    """An sRGB colour in ``[0, 1]`` from a name of :data:`COLOURS`, ``"R,G,B"`` or ``"#rrggbb"``.

    ``"R,G,B"`` values above 1 are read as 8-bit (0-255) values.

    Raises:
        ParameterError: the colour cannot be read.
    """
    if not isinstance(colour, str):
        values = [float(v) for v in colour]
    elif colour.lower() in COLOURS:
        return COLOURS[colour.lower()]
    elif colour.startswith("#") and len(colour) == 7:
        try:
            values = [int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5)]
        except ValueError:
            raise ParameterError(f"cannot read the colour {colour!r}") from None
    else:
        try:
            values = [float(v) for v in colour.split(",")]
        except ValueError:
            raise ParameterError(
                f"cannot read the colour {colour!r}: use a name ({', '.join(COLOURS)}), "
                "R,G,B or #rrggbb"
            ) from None
    if len(values) != 3 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise ParameterError(f"a colour needs three non-negative values, got {colour!r}")
    if max(values) > 1:
        values = [v / 255 for v in values]
    if max(values) > 1:
        raise ParameterError(f"colour values must be at most 255, got {colour!r}")
    return (values[0], values[1], values[2])


def _srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """Linear to sRGB without clipping (odd extension below 0)."""
    a = x.abs()
    y = torch.where(a <= 0.0031308, 12.92 * a, 1.055 * a.clamp_min(1e-12).pow(1 / 2.4) - 0.055)
    return y * torch.sign(x)


def _srgb_decode(y: torch.Tensor) -> torch.Tensor:
    """Decode sRGB to linear without clipping (odd extension below 0)."""
    a = y.abs()
    x = torch.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055).pow(2.4))
    return x * torch.sign(y)


def linear_to_lab(x: torch.Tensor) -> torch.Tensor:
    """CIELab (D65) of linear RGB ``(B, 3, H, W)`` (kornia; values above 1 are allowed)."""
    return kornia.color.rgb_to_lab(_srgb_encode(x))


def lab_to_linear(lab: torch.Tensor) -> torch.Tensor:
    """Linear RGB of CIELab (D65) ``(B, 3, H, W)``, unclipped (kornia)."""
    return _srgb_decode(kornia.color.lab_to_rgb(lab, clip=False))


def colour_ab(colour: str | Sequence[float], like: torch.Tensor) -> torch.Tensor:
    """The ``(1, 2, 1, 1)`` CIELab ``a*, b*`` of a colour for :func:`parse_colour`.

    The colour is an sRGB value, so it goes to Lab as it is (not through the linear decoding
    of :func:`linear_to_lab`); the result has ``like``'s dtype and device.
    """
    rgb = torch.tensor(parse_colour(colour), dtype=like.dtype, device=like.device)
    return kornia.color.rgb_to_lab(rgb.view(1, 3, 1, 1))[:, 1:]
