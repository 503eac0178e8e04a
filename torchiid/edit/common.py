"""Checks, masks, safe division, the white level and the Gaussian filter of the edits."""

from __future__ import annotations

import math

import kornia
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.core.stats import image_quantile

__all__ = ["default_blur", "gaussian"]

#: the smallest denominator, shading level and light peak the edits divide by
EPS = 1e-6


def default_blur(height: int, width: int) -> float:
    """The default Gaussian σ in pixels of the residue filters: 1% of the longer side, >= 1."""
    return max(1.0, 0.01 * max(height, width))


def gaussian(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``(B, C, H, W)`` with σ in pixels (replicated borders)."""
    if sigma <= 0:
        return x
    k = 2 * math.ceil(3 * sigma) + 1
    return kornia.filters.gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="replicate")


def safe_div(a: torch.Tensor, b: torch.Tensor, default: float = 1.0) -> torch.Tensor:
    """``a / b`` where ``|b| > EPS``, else ``default``."""
    ok = b.abs() > EPS
    return torch.where(ok, a / torch.where(ok, b, torch.ones_like(b)), torch.full_like(a, default))


def check_layers(image: torch.Tensor, *others: torch.Tensor | None) -> None:
    """Raise :class:`ShapeError` unless ``image`` is 4-D and every other layer matches its size."""
    if image.dim() != 4:
        raise ShapeError(f"expected a (B, C, H, W) tensor, got shape {tuple(image.shape)}")
    for o in others:
        if o is not None and (o.dim() != 4 or o.shape[-2:] != image.shape[-2:]):
            raise ShapeError(
                f"layer of shape {tuple(o.shape)} does not match the image {tuple(image.shape)}"
            )


def region(mask: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` bool mask (all-true when ``None``)."""
    if mask is None:
        return torch.ones_like(like[:, :1], dtype=torch.bool)
    if mask.dim() == 3:
        mask = mask[:, None] if mask.shape[0] == like.shape[0] and like.shape[0] > 1 else mask[None]
    check_layers(like, mask)
    return mask.to(like.device).bool().expand(like.shape[0], 1, -1, -1)


def white_level(shading: torch.Tensor, q: float = 0.99) -> torch.Tensor:
    """``(B, 1, 1, 1)`` ``q`` quantile of each image's shading luminance (>= EPS)."""
    y = shading.mean(1, keepdim=True)
    return image_quantile(y, q).clamp_min(EPS).view(-1, 1, 1, 1).to(shading)
