"""Texture confidence for the local Retinex prior ``S_l`` (``t_x``, off by default).

``S_l`` ties neighbours of one chromaticity and gives their intensity difference to the shading,
so texture that varies in lightness within one hue (wood grain, tiles' grout, fur, dark print on
a light ground of its hue) goes into the shading pixel by pixel. Light varies smoothly at the
scale of a few pixels except at shadow edges; texture does not. :func:`texture_confidence`
marks pixels whose neighbourhood is dense with fine-scale variation of ``log p``:

``τ_i = median over the (2w + 1)² window of |r|``, ``r = log p − (its local linear fit at
σ = 1 px)`` (:mod:`torchiid.core.local_fit`, inside the mask), ``c_i = exp(−τ_i²/t_x²)``.

A soft shadow or a shading gradient leaves ``r`` near 0; a single sharp step (a crease, a hard
shadow's or a material's edge) or a thin line raises ``|r|`` in a band narrower than half the
window, which the median ignores; texture raises it over most of the window. Sparse print
(text, thin lines) is not texture here either: ``t_h`` handles it.

Two scales, one for each job. The *detection* is at 1 px: at that scale light has no
variation of its own except at edges, which the median ignores, while a coarser fit also sees
the curvature of soft shadows and the band beside a crease and takes them for texture.
Texture whose pattern is coarser than a pixel still has a fine part there (speckle, streaks,
the flanks of wood's rings), which a small ``t_x`` (the ``texture`` preset's) marks while
smooth light, soft shadows and creases keep a confidence near 1.

The *removal* is coarser: :func:`detexture` gives ``S_l`` the image without its fine texture
where it is dense: each pixel's intensity is scaled by ``exp(−(1 − c_i) r'_i)``, ``r'`` the
residual of the local linear fit at ``sigma`` px (chromaticity unchanged), so ``S_l``'s
targets there follow the fit's differences, which keep the shading's gradients and curvature
at larger scales, and the texture stays in ``ρ = I / σ``. The residual at ``σ`` passes a
variation of period ``P`` with gain ``1 − exp(−2π²σ²/P²)``, so the fit must be coarse enough
to take out the whole of a pattern the 1-px detection marks (wood's rings, several pixels
apart); a coarser fit also spreads a hard shadow's edge inside a texture further into the
targets, which bounds ``sigma`` from above (the values and their measurements: the
documentation's Method page). (A pixel confidence of ``S_l`` instead, which asks for equal
shading at textured pairs, flattens the shading of textured curved surfaces as well.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchiid.core.check import as_mask, check_image
from torchiid.core.exceptions import ParameterError
from torchiid.core.local_fit import local_linear_residual

__all__ = ["REMOVAL_SIGMA", "detexture", "texture_confidence"]

#: scale (px) of the local linear fit whose residual :func:`detexture` takes out (the
#: parameter ``t_x_sigma``)
REMOVAL_SIGMA = 5.0


def texture_confidence(
    image: torch.Tensor,
    t_x: float,
    mask: torch.Tensor | None = None,
    dark_eps: float = 1e-4,
    window: int = 4,
) -> torch.Tensor:
    """``exp(−τ²/t_x²)``: 1 away from fine texture, near 0 inside it (see the module notes).

    Args:
        image: ``(B, 3, H, W)`` linear RGB.
        t_x: texture deviation, in log-intensity (RMS of the fine-scale residual).
        mask: optional ``(B, 1, H, W)`` bool; only pixels inside enter the fits and means.
        dark_eps: intensity floor before the log.
        window: half-side ``w`` (px) of the median's square window.

    Returns:
        ``(B, 1, H, W)`` in the image's dtype.
    """
    check_image(image, "image", channels=3)
    if not t_x > 0 or not window > 0:
        raise ParameterError(f"t_x and window must be > 0, got t_x={t_x}, window={window}")
    logp = image.mean(dim=1, keepdim=True).clamp_min(dark_eps).log()
    r = local_linear_residual(logp, mask, sigma=1.0).abs()
    if mask is not None:
        r = torch.where(as_mask(mask, r), r, torch.nan)  # outside pixels take no part
    b, _, h, w = r.shape
    pad = F.pad(r, (window,) * 4, value=float("nan"))
    tau = F.unfold(pad, 2 * window + 1).view(b, -1, h, w).nanmedian(1, keepdim=True).values
    return torch.exp(-((tau.nan_to_num(0.0) / t_x) ** 2)).to(image.dtype)


def detexture(
    image: torch.Tensor,
    t_x: float,
    mask: torch.Tensor | None = None,
    dark_eps: float = 1e-4,
    sigma: float = REMOVAL_SIGMA,
) -> torch.Tensor:
    """``image`` without its fine texture where :func:`texture_confidence` finds it dense.

    Returns:
        ``(B, 3, H, W)``: ``image · exp(−(1 − c) · r')`` with ``c`` the texture confidence and
        ``r'`` the residual of ``log p`` after its local linear fit at ``sigma`` px.
    """
    c = texture_confidence(image, t_x, mask, dark_eps).double()
    logp = image.mean(dim=1, keepdim=True).clamp_min(dark_eps).log()
    r = local_linear_residual(logp, mask, sigma=sigma)
    return (image.double() * torch.exp(-(1 - c) * r)).to(image.dtype)
