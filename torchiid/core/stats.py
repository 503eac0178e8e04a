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
            out.append(_quantile(v.float(), q, interpolation).cpu())
    return torch.stack(out).to(x.device, x.dtype)


def _quantile(v: torch.Tensor, q: float, interpolation: str) -> torch.Tensor:
    """``torch.quantile(v, q, interpolation=...)`` of a 1-D tensor by selection, not sorting.

    The one or two order statistics the quantile needs come from ``torch.kthvalue`` (linear
    time, where ``torch.quantile`` sorts every value), at the ranks
    ``torch.quantile`` computes (``q (n − 1)`` in ``v``'s dtype, then floor, ceil or round)
    and combined as it does (``lerp``), so the value is the same. NaN values, other devices
    and ``q`` outside [0, 1] go to ``torch.quantile`` itself.
    """
    if not 0 <= q <= 1 or v.device.type != "cpu" or bool(torch.isnan(v).any()):
        return torch.quantile(v, q, interpolation=interpolation)
    rank = torch.tensor(q, dtype=v.dtype) * (v.numel() - 1)
    if interpolation in ("lower", "higher", "nearest"):
        r = {"lower": rank.floor(), "higher": rank.ceil(), "nearest": rank.round()}
        return torch.kthvalue(v, int(r[interpolation]) + 1).values
    if interpolation not in ("linear", "midpoint"):
        return torch.quantile(v, q, interpolation=interpolation)  # its own error
    lo, hi = int(rank.floor()), int(rank.ceil())
    below = torch.kthvalue(v, lo + 1).values
    above = below if hi == lo else torch.kthvalue(v, hi + 1).values
    weight = rank - lo if interpolation == "linear" else torch.tensor(0.5, dtype=v.dtype)
    return torch.lerp(below, above, weight)
