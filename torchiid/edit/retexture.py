"""Albedo replacement: a texture image's colours as the reflectance inside a mask."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from torchiid.core.check import check_finite
from torchiid.core.exceptions import ParameterError
from torchiid.edit.common import check_edit_numbers, check_layers, region

__all__ = ["replace_albedo"]


def replace_albedo(
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    mask: torch.Tensor,
    texture: torch.Tensor,
    *,
    fit: str = "tile",
    scale: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Put a texture image's colours as the reflectance inside ``mask`` and keep the shading.

    Args:
        reflectance: ``(B, 3, H, W)``.
        shading: ``(B, 1|3, H, W)``.
        mask: ``(B, 1, H, W)`` bool, the region.
        texture: ``(3, h, w)`` or ``(1, 3, h, w)`` linear albedo (clipped to ``[0, 1]``).
        fit: ``"tile"`` (repeat from the mask's bounding box's top-left corner, the texture
            resized by ``scale``) or ``"stretch"`` (resize to the bounding box).
        scale: size factor of the tiles (``"tile"`` only).

    Returns:
        ``(edited image, edited reflectance)``.
    """
    check_layers(reflectance, shading)
    m = region(mask, reflectance)
    tex = texture if texture.dim() == 4 else texture[None]
    tex = tex[:1].to(reflectance).clamp(0, 1)
    if fit not in ("tile", "stretch"):
        raise ParameterError(f"fit must be tile or stretch, got {fit!r}")
    check_edit_numbers(reflectance, scale=scale, texture=tex if fit == "tile" else None)
    check_finite(tex, "texture")
    new_r = reflectance.clone()
    for b in range(reflectance.shape[0]):
        ys, xs = torch.nonzero(m[b, 0], as_tuple=True)
        if ys.numel() == 0:
            raise ParameterError("the mask holds no pixel")
        y0, y1, x0, x1 = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
        patch = _patch(tex, (y1 - y0, x1 - x0), fit, scale)
        inside = m[b, :, y0:y1, x0:x1]
        new_r[b, :, y0:y1, x0:x1] = torch.where(inside, patch[0], new_r[b, :, y0:y1, x0:x1])
    return new_r * shading, new_r


def _patch(tex: torch.Tensor, size: tuple[int, int], fit: str, scale: float) -> torch.Tensor:
    """``tex`` ``(1, 3, h, w)`` brought to the bounding box's ``size`` by ``fit``."""
    bh, bw = size
    if fit == "stretch":
        return F.interpolate(tex, size=(bh, bw), mode="bilinear", align_corners=False)
    if scale != 1.0:
        tiles = (max(1, round(tex.shape[-2] * scale)), max(1, round(tex.shape[-1] * scale)))
        tex = F.interpolate(tex, size=tiles, mode="bilinear", align_corners=False)
    reps = (math.ceil(bh / tex.shape[-2]), math.ceil(bw / tex.shape[-1]))
    return tex.repeat(1, 1, *reps)[..., :bh, :bw]
