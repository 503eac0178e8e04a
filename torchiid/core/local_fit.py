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

__all__ = ["local_linear_residual"]


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
        conv_dtype: the precision of the window sums (float32 is about ten times faster on
            a CPU; the fit's algebra is float64 either way).

    Returns:
        ``(B, C, H, W)`` residual in float64.
    """
    check_shape(x, ("B", "C", "H", "W"), "x")
    if not sigma > 0:
        raise ParameterError(f"sigma must be > 0, got {sigma}")
    b, c, h, w = x.shape
    m = as_mask(region, x[:, :1], "region").to(conv_dtype)
    v = (x.to(conv_dtype) * m).reshape(b * c, 1, h, w)
    k = _kernels(float(sigma), conv_dtype, x.device)
    # moments Σ G·u^i·v^j·m over the window, u, v the offsets (i + j <= 2), and the same with x
    pairs = {"1": (0, 0), "u": (0, 1), "v": (1, 0), "uu": (0, 2), "uv": (1, 1), "vv": (2, 0)}
    if region is None:
        # m = 1: each moment is the product of a column and a row profile (zero padding)
        ones_y = torch.ones(1, 1, h, 1, dtype=conv_dtype, device=x.device)
        ones_x = torch.ones(1, 1, 1, w, dtype=conv_dtype, device=x.device)
        one = torch.ones(1, dtype=conv_dtype, device=x.device)
        col = {i: _sep(ones_y, k[i], one).double() for i in (0, 1, 2)}
        row = {j: _sep(ones_x, one, k[j]).double() for j in (0, 1, 2)}
        mom = {n: col[i] * row[j] for n, (i, j) in pairs.items()}
    else:
        mom = {n: _sep(m, k[i], k[j]).double() for n, (i, j) in pairs.items()}
    rhs = [_sep(v, k[i], k[j]).double().view(b, c, h, w) for i, j in ((0, 0), (0, 1), (1, 0))]
    # the intercept from the first row of the symmetric 3×3 system's inverse (its cofactors);
    # a small ridge on the slopes keeps the system regular where the region is a thin strip
    ridge = 1e-10 * sigma**2 * mom["1"].clamp_min(1e-12)
    a00, a01, a02 = mom["1"].clamp_min(1e-12), mom["u"], mom["v"]
    a11, a12, a22 = mom["uu"] + ridge, mom["uv"], mom["vv"] + ridge
    c0, c1, c2 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    det = a00 * c0 + a01 * c1 + a02 * c2
    fit = (c0 * rhs[0] + c1 * rhs[1] + c2 * rhs[2]) / det
    # outside the region the moments vanish and so does det: those pixels are 0, not 0/0
    residual: torch.Tensor = torch.where(m.double() > 0, x.double() - fit, 0.0)
    return residual
