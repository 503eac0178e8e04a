"""Recolouring: new hue and chroma for an object's reflectance, lightness and shading kept."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from torchiid.edit.colour import colour_ab, lab_to_linear, linear_to_lab
from torchiid.edit.common import check_edit_numbers, check_layers, region

__all__ = ["Recolour", "recolour"]


def recolour(
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    mask: torch.Tensor,
    *,
    hue: float = 0.0,
    chroma: float = 1.0,
    colour: str | Sequence[float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Change the hue and chroma of the reflectance inside ``mask``; keep lightness and shading.

    In CIELab the reflectance's ``(a*, b*)`` inside the mask are (1) moved so that their mean
    is the ``colour``'s ``(a*, b*)`` when ``colour`` is given, (2) rotated by ``hue`` degrees
    and (3) multiplied by ``chroma``; ``L*`` (the lightness texture) is unchanged. The result
    is clipped to ``[0, 1]`` (an albedo), which changes ``L*`` only for out-of-gamut colours.
    Outside the mask nothing changes (bit for bit).

    Args:
        reflectance: ``(B, 3, H, W)`` albedo.
        shading: ``(B, 1|3, H, W)``.
        mask: ``(B, 1, H, W)`` bool, the object.
        hue: rotation of the hue angle in degrees.
        chroma: chroma factor (0: gray, 1: unchanged).
        colour: target colour (see :func:`~torchiid.edit.colour.parse_colour`) for the
            region's mean chroma.

    Returns:
        ``(edited image, edited reflectance)``.
    """
    check_layers(reflectance, shading)
    check_edit_numbers(reflectance, hue=hue, chroma=chroma)
    m = region(mask, reflectance)
    lab = linear_to_lab(reflectance.clamp(0, 1))
    ab = lab[:, 1:]
    if colour is not None:
        target = colour_ab(colour, lab)
        w = m.to(ab.dtype)
        mean = (ab * w).sum((2, 3), keepdim=True) / w.sum((2, 3), keepdim=True).clamp_min(1)
        ab = ab - mean + target
    t = math.radians(hue)
    a = ab[:, :1] * math.cos(t) - ab[:, 1:] * math.sin(t)
    bb = ab[:, :1] * math.sin(t) + ab[:, 1:] * math.cos(t)
    new = lab_to_linear(torch.cat([lab[:, :1], a * chroma, bb * chroma], 1)).clamp(0, 1)
    new_r = torch.where(m, new, reflectance)
    return new_r * shading, new_r


class Recolour(nn.Module):
    """:func:`recolour` as a module; ``forward(R, S, mask)`` returns ``(image, reflectance)``."""

    def __init__(self, hue: float = 0.0, chroma: float = 1.0, colour=None) -> None:
        super().__init__()
        self.hue, self.chroma, self.colour = hue, chroma, colour

    def forward(self, reflectance, shading, mask):  # noqa: D102
        return recolour(
            reflectance, shading, mask, hue=self.hue, chroma=self.chroma, colour=self.colour
        )
