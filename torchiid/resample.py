"""Working-resolution helpers: downsampling and edge-aware upsampling of layers.

Large photos are decomposed at a working resolution; the log-shading is brought back to full
resolution with guided upsampling (He & Sun 2015, "Fast guided filter"): the local linear model
``log S ≈ a · log Y + b`` (``Y`` the image's luminance) is fitted in box windows at the low
resolution, its coefficients ``a, b`` are upsampled bilinearly, and applied to the full-resolution
guide. Shading edges therefore follow the full-resolution image, so outputs are never blurry.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["working_size", "downsample", "guided_upsample"]


def working_size(height: int, width: int, max_side: int) -> tuple[int, int]:
    """``(h, w)`` with the longer side at most ``max_side`` (0 = unchanged), aspect kept."""
    if max_side <= 0 or max(height, width) <= max_side:
        return height, width
    s = max_side / max(height, width)
    return max(1, round(height * s)), max(1, round(width * s))


def downsample(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Area-average ``(B, C, H, W)`` to ``size`` (antialiased); identity if already that size."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="area")


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    return F.avg_pool2d(F.pad(x, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)


def guided_upsample(
    low: torch.Tensor,
    guide_low: torch.Tensor,
    guide_full: torch.Tensor,
    radius: int = 2,
    eps: float = 1e-3,
) -> torch.Tensor:
    """Edge-aware upsampling of a one-channel map by a fast guided filter.

    Args:
        low: ``(B, 1, h, w)`` the map to upsample (e.g. log-shading).
        guide_low: ``(B, 1, h, w)`` the guide at low resolution (e.g. log-luminance).
        guide_full: ``(B, 1, H, W)`` the same guide at full resolution.
        radius: box radius of the local linear fit, in low-resolution pixels.
        eps: regulariser of the fit (in squared guide units).

    Returns:
        ``(B, 1, H, W)``.
    """
    if tuple(low.shape[-2:]) == tuple(guide_full.shape[-2:]):
        return low
    mean_g = _box(guide_low, radius)
    mean_x = _box(low, radius)
    cov = _box(guide_low * low, radius) - mean_g * mean_x
    var = _box(guide_low * guide_low, radius) - mean_g * mean_g
    a = cov / (var + eps)
    b = mean_x - a * mean_g
    size = guide_full.shape[-2:]
    a_up = F.interpolate(_box(a, radius), size=size, mode="bilinear", align_corners=False)
    b_up = F.interpolate(_box(b, radius), size=size, mode="bilinear", align_corners=False)
    return a_up * guide_full + b_up
