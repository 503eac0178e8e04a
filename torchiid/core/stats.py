"""Quantiles of large images without the size limit of ``torch.quantile``.

``torch.quantile`` refuses inputs of more than 2^24 elements (a 16.7-megapixel layer), and
sorting a whole 24-megapixel layer to find one value costs time and memory. These helpers take
the quantile on a regular sub-grid of at most about a megapixel per image, which is plenty for
the scale factors and thresholds torchiid derives from quantiles.
"""

from __future__ import annotations

import math

import torch

__all__ = ["image_quantile", "subgrid"]

#: pixels per image kept by :func:`subgrid`
SUBGRID_PIXELS = 1 << 20


def subgrid(x: torch.Tensor, limit: int = SUBGRID_PIXELS) -> tuple[torch.Tensor, int]:
    """A regular sub-grid ``x[..., ::step, ::step]`` with at most about ``limit`` pixels.

    Returns:
        ``(view, step)``.
    """
    step = max(1, int(math.ceil(math.sqrt(x.shape[-2] * x.shape[-1] / limit))))
    return x[..., ::step, ::step], step


def image_quantile(
    x: torch.Tensor,
    q: float,
    mask: torch.Tensor | None = None,
    default: float = 1.0,
    interpolation: str = "linear",
) -> torch.Tensor:
    """Per-image ``q``-quantile of ``(B, C, H, W)`` values (channels pooled) inside ``mask``.

    Args:
        x: the values.
        q: the quantile in [0, 1].
        mask: ``(B, 1, H, W)`` bool, or ``None`` for every pixel.
        default: the value for an image with no pixel inside the mask.
        interpolation: as in ``torch.quantile``.

    Returns:
        ``(B,)`` in the dtype and device of ``x``.
    """
    xs, step = subgrid(x)
    ms = None if mask is None else mask[..., ::step, ::step]
    out = []
    for i in range(x.shape[0]):
        v = xs[i].reshape(-1) if ms is None else xs[i][ms[i].expand_as(xs[i])].reshape(-1)
        if v.numel() == 0:
            out.append(torch.tensor(float(default)))
        else:
            out.append(torch.quantile(v.float(), q, interpolation=interpolation).cpu())
    return torch.stack(out).to(x.device, x.dtype)
