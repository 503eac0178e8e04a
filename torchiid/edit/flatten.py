"""Texture removal: one flat reflectance colour inside a mask, the shading kept."""

from __future__ import annotations

import torch

from torchiid.core.exceptions import ParameterError
from torchiid.edit.common import check_layers, region

__all__ = ["remove_texture"]


def remove_texture(
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    mask: torch.Tensor,
    *,
    flatten: str = "mean",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace the reflectance inside ``mask`` by one flat colour and keep the shading.

    Args:
        reflectance: ``(B, 3, H, W)``.
        shading: ``(B, 1|3, H, W)``.
        mask: ``(B, 1, H, W)`` bool, the region.
        flatten: ``"mean"`` (linear mean of the region's reflectance) or ``"median"``.

    Returns:
        ``(edited image, edited reflectance)``.
    """
    check_layers(reflectance, shading)
    m = region(mask, reflectance)
    flat = torch.empty(reflectance.shape[0], 3, 1, 1, dtype=reflectance.dtype)
    for b in range(reflectance.shape[0]):
        inside = reflectance[b][:, m[b, 0]]
        if inside.numel() == 0:
            raise ParameterError("the mask holds no pixel")
        if flatten == "mean":
            flat[b] = inside.mean(1).view(3, 1, 1)
        elif flatten == "median":
            flat[b] = inside.median(1).values.view(3, 1, 1)
        else:
            raise ParameterError(f"flatten must be mean or median, got {flatten!r}")
    new_r = torch.where(m, flat.to(reflectance.device), reflectance)
    return new_r * shading, new_r
