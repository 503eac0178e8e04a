"""Gaussian-weighted local fits: what is left of an image after its local linear trend.

:func:`local_linear_residual` subtracts, at every pixel, the plane fitted by weighted least
squares to its neighbourhood (Gaussian weights, inside a region), so constants and linear ramps
vanish and fine-scale variation remains. Used by the texture measure
(:mod:`torchiid.eval.texture`) and the texture confidence of the shading prior
(:mod:`torchiid.priors.texture`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from torchiid.core.check import as_mask, check_shape
from torchiid.core.exceptions import ParameterError

__all__ = ["local_linear_residual", "residual_in"]


def _kernels(sigma: float, dtype: torch.dtype, device: torch.device) -> dict[int, torch.Tensor]:
    """1-D Gaussian kernels times ``d^p`` (p = 0, 1, 2), ``d`` the offset in pixels."""
    r = max(1, int(math.ceil(3 * sigma)))
    d = torch.arange(-r, r + 1, dtype=dtype, device=device)
    g = torch.exp(-0.5 * (d / sigma) ** 2)
    g = g / g.sum()
    return {p: g * d**p for p in (0, 1, 2)}


def _sep(x: torch.Tensor, ky: torch.Tensor, kx: torch.Tensor) -> torch.Tensor:
    """Separable cross-correlation of ``(N, 1, H, W)`` with zero padding (``Σ_d k(d) x(p + d)``).

    As shifted sums: a one-channel convolution with a 7- to 31-tap kernel takes several times
    longer on a CPU in ``conv2d`` than the same number of array additions.
    """
    ry, rx = ky.numel() // 2, kx.numel() // 2
    h, w = x.shape[-2:]
    pad = F.pad(x, (0, 0, ry, ry))
    taps: list[float] = ky.tolist()
    y = pad[..., :h, :] * taps[0]
    for i in range(1, len(taps)):
        y.add_(pad[..., i : i + h, :], alpha=taps[i])
    pad = F.pad(y, (rx, rx))
    taps = kx.tolist()
    out: torch.Tensor = pad[..., :w] * taps[0]
    for i in range(1, len(taps)):
        out.add_(pad[..., i : i + w], alpha=taps[i])
    return out


def _border_bands(n: int, r: int) -> list[tuple[int, int, int, int]]:
    """The slices that give a radius-``r`` window sum within ``r`` of either end of ``n``.

    Each is ``(start, size, keep, length)``: the sums of the input slice ``[start, start +
    size)``, zero-padded, are right for its outputs ``[keep, keep + length)`` (those whose
    window stops short of the slice's inner end).
    """
    if n <= 4 * r:
        return [(0, n, 0, n)]
    return [(0, 2 * r, 0, r), (n - 2 * r, 2 * r, r, r)]


def local_linear_residual(
    x: torch.Tensor,
    region: torch.Tensor | None = None,
    sigma: float = 3.0,
    conv_dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """``x`` minus its Gaussian-weighted local linear fit inside ``region`` (0 outside it).

    At each pixel ``p`` the plane ``a + b·(q_x − p_x) + c·(q_y − p_y)`` minimising
    ``Σ_q G_σ(q − p) m_q (x_q − plane_q)²`` over the pixels ``q`` of the region is fitted,
    and ``x_p − a`` returned. Constants and linear ramps give exactly 0. The fit's 3×3
    system depends only on the region, so the channels of ``x`` share it.

    Args:
        x: ``(B, C, H, W)`` values (e.g. a log-shading), each channel fitted on its own.
        region: ``(B, 1, H, W)`` mask as in :func:`~torchiid.core.check.as_mask`; ``None``:
            every pixel.
        sigma: Gaussian scale of the fit, in pixels.
        conv_dtype: the precision of the window sums, the fit and the residual (float32 is
            several times faster on a CPU; with a region, the fit's 3×3 algebra is float64
            either way, without one it is well conditioned in either).

    Returns:
        ``(B, C, H, W)`` residual in float64 (a copy of :func:`residual_in`'s).
    """
    return residual_in(x, region, sigma, conv_dtype).double()


def residual_in(
    x: torch.Tensor,
    region: torch.Tensor | None,
    sigma: float,
    conv_dtype: torch.dtype,
) -> torch.Tensor:
    """:func:`local_linear_residual` in ``conv_dtype`` (no float64 copy of a float32 result)."""
    check_shape(x, ("B", "C", "H", "W"), "x")
    if not sigma > 0:
        raise ParameterError(f"sigma must be > 0, got {sigma}")
    b, c, h, w = x.shape
    k = _kernels(float(sigma), conv_dtype, x.device)
    if region is None:
        return _residual_everywhere(x, k, sigma, conv_dtype)
    m = as_mask(region, x[:, :1], "region").to(conv_dtype)
    v = (x.to(conv_dtype) * m).reshape(b * c, 1, h, w)
    mom = {n: _sep(m, k[i], k[j]).double() for n, (i, j) in _PAIRS.items()}
    w0, w1, w2 = _intercept_weights(mom, sigma)
    fit = _sep(v, k[0], k[0]).double().view(b, c, h, w).mul_(w0)
    fit.addcmul_(_sep(v, k[0], k[1]).double().view(b, c, h, w), w1)
    fit.addcmul_(_sep(v, k[1], k[0]).double().view(b, c, h, w), w2)
    # outside the region the moments vanish and so does det: those pixels are 0, not 0/0
    residual: torch.Tensor = torch.where(m.double() > 0, x.double() - fit, 0.0)
    return residual.to(conv_dtype)


#: the moments ``Σ G·v^i·u^j·m`` of the fit's 3×3 system (``v``, ``u`` the row and column
#: offsets, ``i + j <= 2``), as ``(i, j)``: the powers of the column and row kernels
_PAIRS = {"1": (0, 0), "u": (0, 1), "v": (1, 0), "uu": (0, 2), "uv": (1, 1), "vv": (2, 0)}


def _intercept_weights(
    mom: dict[str, torch.Tensor], sigma: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The first row of the inverse of each pixel's symmetric 3×3 system (its cofactors).

    The intercept is ``w0·Σ G m x + w1·Σ G u m x + w2·Σ G v m x``. A small ridge on the
    slopes keeps the system regular where the region is a thin strip.
    """
    ridge = 1e-10 * sigma**2 * mom["1"].clamp_min(1e-12)
    a00, a01, a02 = mom["1"].clamp_min(1e-12), mom["u"], mom["v"]
    a11, a12, a22 = mom["uu"] + ridge, mom["uv"], mom["vv"] + ridge
    c0, c1, c2 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    det = a00 * c0 + a01 * c1 + a02 * c2
    return c0 / det, c1 / det, c2 / det


def _representatives(n: int, r: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``(kept, of)``: the rows within ``r`` of either end of ``n`` and one whole row between.

    Every row farther than ``r`` from the ends has the same (whole) window, so a quantity of
    the window alone is computed at ``kept`` and spread back by ``of`` (each row's index
    into ``kept``).
    """
    every = torch.arange(n, device=device)
    if n <= 2 * r + 1:
        return every, every
    kept = torch.cat([every[: r + 1], every[n - r :]])
    of = every.clamp(max=r)
    of[n - r :] = torch.arange(r + 1, 2 * r + 1, device=device)
    return kept, of


def _profile(kernel: torch.Tensor, n: int, at: torch.Tensor) -> torch.Tensor:
    """``Σ_d kernel(d)`` over the taps ``d`` with ``0 <= y + d < n``, at the rows ``y`` in ``at``.

    The window sum of a row of ones, zero-padded, from the kernel's cumulative sums (in
    float64).
    """
    r = kernel.numel() // 2
    sums = F.pad(kernel.double().cumsum(0), (1, 0))
    first = (r - at).clamp(min=0)  # the first tap inside, d = −y
    last = (n - 1 - at).clamp(max=r) + r  # the last, d = n − 1 − y
    return sums[last + 1] - sums[first]


def _residual_everywhere(
    x: torch.Tensor, k: dict[int, torch.Tensor], sigma: float, conv_dtype: torch.dtype
) -> torch.Tensor:
    """:func:`local_linear_residual` without a region, in ``conv_dtype``.

    Each moment is then the product of a column and a row profile (zero padding), which
    change only within ``r`` of the borders: the fit's weights are solved there and on one
    whole row and column (:func:`_representatives`). Away from the borders the first moments
    vanish and with them ``w1`` (beyond ``r`` columns of the left and right borders) and
    ``w2`` (beyond ``r`` rows of the top and bottom), so the slopes' sums are taken in those
    bands only. The weights are well conditioned without a region: the fit is in the sums'
    precision.
    """
    b, c, h, w = x.shape
    r, dev, dt = k[0].numel() // 2, x.device, conv_dtype
    (rows, of_y), (cols, of_x) = _representatives(h, r, dev), _representatives(w, r, dev)
    col = {i: _profile(k[i], h, rows).view(1, 1, -1, 1) for i in (0, 1, 2)}
    row = {j: _profile(k[j], w, cols).view(1, 1, 1, -1) for j in (0, 1, 2)}
    mom = {n: col[i] * row[j] for n, (i, j) in _PAIRS.items()}
    w0, w1, w2 = (wt.to(dt)[..., of_y, :] for wt in _intercept_weights(mom, sigma))
    v = x.to(dt).reshape(b * c, 1, h, w)
    fit = _sep(v, k[0], k[0]).view(b, c, h, w).mul_(w0[..., of_x])
    for dim, (ki, kj), weight in ((-1, (0, 1), w1), (-2, (1, 0), w2)):
        cuts = _border_bands(x.shape[dim], r)
        # both bands' sums in one call (stacked on the batch axis): fewer small operations
        parts = torch.cat([v.narrow(dim, start, size) for start, size, _, _ in cuts])
        sums_of = _sep(parts, k[ki], k[kj]).chunk(len(cuts))
        for (start, _, keep, length), sums in zip(cuts, sums_of, strict=True):
            at = start + keep
            band = weight.narrow(dim, at, length) if dim == -2 else weight
            band = band[..., of_x[at : at + length]] if dim == -1 else band[..., of_x]
            sums = sums.narrow(dim, keep, length).reshape(b, c, *band.shape[-2:])
            fit.narrow(dim, at, length).addcmul_(sums, band)
    return fit.neg_().add_(x)  # x − fit, in place
