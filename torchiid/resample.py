"""Working-resolution helpers: downsampling and edge-aware upsampling of layers.

Large photos are decomposed at a working resolution; the log-shading is brought back to full
resolution with guided upsampling (He & Sun 2015, "Fast guided filter"): the local linear model
``log S ≈ a · log Y + b`` (``Y`` the image's luminance) is fitted in box windows at the low
resolution, its coefficients ``a, b`` are upsampled bilinearly, and applied to the full-resolution
guide. Where the shading follows the image (a shadow edge) ``a ≈ 1`` and the edge is as sharp as
the photo's; across a reflectance edge the shading does not follow the image, ``a ≈ 0``, and the
shading stays smooth, so no halo is copied into it.

Memory: :class:`GuidedUpsampler` evaluates the full-resolution result in bands of rows
(:func:`row_bands`), so besides its output only one band's temporaries exist at a time — the
cost of a 24-megapixel photo is its few full-resolution layers, not a dozen float copies.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from torchiid.core.bands import BAND_PIXELS as BAND_PIXELS  # the bands of row_bands
from torchiid.core.bands import row_bands

__all__ = [
    "working_size",
    "downsample",
    "guided_upsample",
    "GuidedUpsampler",
    "bilinear_rows",
    "row_bands",
]


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


def _linear_taps(
    n_in: int, n_out: int, start: int, stop: int, device: torch.device, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Source indices and weight of linear interpolation, ``align_corners=False`` convention."""
    dst = torch.arange(start, stop, device=device, dtype=torch.float64)
    src = ((dst + 0.5) * (n_in / n_out) - 0.5).clamp_min(0)
    i0 = src.floor().long().clamp_max(n_in - 1)
    i1 = (i0 + 1).clamp_max(n_in - 1)
    return i0, i1, (src - i0).to(dtype)


def bilinear_rows(x: torch.Tensor, size: tuple[int, int], rows: slice) -> torch.Tensor:
    """Rows ``rows`` of ``F.interpolate(x, size, mode="bilinear", align_corners=False)``.

    Computes only the requested band, so a large upsampled map never has to exist whole.

    Shape:
        x ``(B, C, h, w)`` -> ``(B, C, len(rows), W)`` with ``(H, W) = size``.
    """
    big_h, big_w = size
    h, w = x.shape[-2:]
    y0, y1, ly = _linear_taps(h, big_h, rows.start, rows.stop, x.device, x.dtype)
    x0, x1, lx = _linear_taps(w, big_w, 0, big_w, x.device, x.dtype)
    ly = ly.view(-1, 1)
    t = x[:, :, y0] * (1 - ly) + x[:, :, y1] * ly
    return t[..., x0] * (1 - lx) + t[..., x1] * lx


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    return F.avg_pool2d(F.pad(x, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)


class GuidedUpsampler:
    """Fast guided upsampling of a one-channel map, evaluated band by band.

    Args:
        low: ``(B, 1, h, w)`` the map to upsample (e.g. log-shading).
        guide_low: ``(B, 1, h, w)`` the guide at low resolution (e.g. log-luminance).
        size: the full resolution ``(H, W)``.
        radius: box radius of the local linear fit, in low-resolution pixels.
        eps: regulariser of the fit (in squared guide units).
        weight: optional ``(B, 1, h, w)`` weights in [0, 1] of the low-resolution pixels (the
            share of each inside a mask): every box mean of the fit is weighted, so pixels
            outside a mask, whose values mean nothing, do not bend the fit near its edge.

    Call :meth:`band` with the full-resolution guide's rows to get those rows of the result.
    """

    def __init__(
        self,
        low: torch.Tensor,
        guide_low: torch.Tensor,
        size: tuple[int, int],
        radius: int = 2,
        eps: float = 1e-3,
        weight: torch.Tensor | None = None,
    ) -> None:
        if weight is None:

            def box(x: torch.Tensor) -> torch.Tensor:
                return _box(x, radius)

        else:  # weighted means: pixels of weight 0 (outside a mask) do not enter any fit
            den = _box(weight, radius)
            inv = torch.where(den > 1e-6, 1 / den.clamp_min(1e-6), torch.zeros_like(den))

            def box(x: torch.Tensor) -> torch.Tensor:
                return _box(weight * x, radius) * inv

        mean_g = box(guide_low)
        mean_x = box(low)
        cov = box(guide_low * low) - mean_g * mean_x
        var = box(guide_low * guide_low) - mean_g * mean_g
        a = cov / (var + eps)
        b = mean_x - a * mean_g
        if weight is not None:  # windows with no pixel inside: constant continuation
            a = torch.where(den > 1e-6, a, torch.zeros_like(a))
            b = torch.where(den > 1e-6, b, low)
            self.a, self.b = box(a), box(b)
            self.a = torch.where(den > 1e-6, self.a, a)
            self.b = torch.where(den > 1e-6, self.b, b)
        else:
            self.a = _box(a, radius)
            self.b = _box(b, radius)
        self.size = (int(size[0]), int(size[1]))

    def band(self, rows: slice, guide_rows: torch.Tensor) -> torch.Tensor:
        """Rows ``rows`` of the result from the same rows of the full-resolution guide."""
        a = bilinear_rows(self.a, self.size, rows)
        b = bilinear_rows(self.b, self.size, rows)
        return a.mul_(guide_rows).add_(b)

    def full(
        self, guide: Callable[[slice], torch.Tensor], out: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The whole ``(B, 1, H, W)`` result; ``guide(rows)`` gives the guide's rows."""
        b = self.a.shape[0]
        if out is None:
            out = self.a.new_empty(b, 1, *self.size)
        for rows in row_bands(*self.size):
            out[:, :, rows] = self.band(rows, guide(rows))
        return out


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
    up = GuidedUpsampler(low, guide_low, tuple(guide_full.shape[-2:]), radius, eps)
    return up.full(lambda rows: guide_full[:, :, rows])
