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
    """Separable cross-correlation of ``(N, 1, H, W)`` with zero padding (``Σ_d k(d) x(p + d)``)."""
    r = ky.numel() // 2
    x = F.conv2d(x, ky.view(1, 1, -1, 1), padding=(r, 0))
    return F.conv2d(x, kx.view(1, 1, 1, -1), padding=(0, r))


def local_linear_residual(
    x: torch.Tensor, region: torch.Tensor | None = None, sigma: float = 3.0
) -> torch.Tensor:
    """``x`` minus its Gaussian-weighted local linear fit inside ``region`` (0 outside it).

    At each pixel ``p`` the plane ``a + b·(q_x − p_x) + c·(q_y − p_y)`` minimising
    ``Σ_q G_σ(q − p) m_q (x_q − plane_q)²`` over the pixels ``q`` of the region is fitted,
    and ``x_p − a`` returned. Constants and linear ramps give exactly 0.

    Args:
        x: ``(B, 1, H, W)`` values (e.g. a log-shading).
        region: mask as in :func:`~torchiid.core.check.as_mask`; ``None``: every pixel.
        sigma: Gaussian scale of the fit, in pixels.

    Returns:
        ``(B, 1, H, W)`` residual in float64.
    """
    check_shape(x, ("B", 1, "H", "W"), "x")
    if not sigma > 0:
        raise ParameterError(f"sigma must be > 0, got {sigma}")
    m = as_mask(region, x, "region").double()
    v = x.double() * m
    k = _kernels(float(sigma), torch.float64, x.device)
    # moments Σ G·u^i·v^j·m over the window, u, v the offsets (i + j <= 2), and the same with x
    pairs = {"1": (0, 0), "u": (0, 1), "v": (1, 0), "uu": (0, 2), "uv": (1, 1), "vv": (2, 0)}
    mom = {n: _sep(m, k[i], k[j]) for n, (i, j) in pairs.items()}
    rhs = torch.stack([_sep(v, k[i], k[j]) for i, j in ((0, 0), (0, 1), (1, 0))], -1)
    a = torch.stack(
        [
            torch.stack([mom["1"], mom["u"], mom["v"]], -1),
            torch.stack([mom["u"], mom["uu"], mom["uv"]], -1),
            torch.stack([mom["v"], mom["uv"], mom["vv"]], -1),
        ],
        -2,
    )
    # a small ridge on the slopes keeps the system regular where the region is a thin strip
    ridge = 1e-10 * sigma**2 * mom["1"].clamp_min(1e-12)
    a = a + torch.diag_embed(torch.stack([torch.zeros_like(ridge), ridge, ridge], -1))
    a[..., 0, 0] = a[..., 0, 0].clamp_min(1e-12)
    fit: torch.Tensor = torch.linalg.solve(a, rhs.unsqueeze(-1))[..., 0, 0]
    residual: torch.Tensor = (x.double() - fit) * m
    return residual
