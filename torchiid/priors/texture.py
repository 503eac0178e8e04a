"""Texture confidence for the local Retinex prior ``S_l`` (``t_x``; ``t_xc``, its colour marks).

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

**Texture that changes colour** (``t_xc``, the ``default``'s marks). Fine relief and fine
texture look alike in lightness, but light of one colour scales every channel alike, so the
fine variation that shading makes leaves the chromaticity as it is, while a surface's own
pattern almost always changes colour with its lightness (darker wood grain is redder, a
tabby's dark stripes browner). :func:`colour_texture_evidence` measures that in the same
window as ``τ``: the fine residuals (1-px local linear fits) of the log-chromaticity ``q`` and
of the log-intensity ``ℓ``, their window covariance, the slope ``β = ‖cov(q, ℓ)‖ / var(ℓ)``
(log-chromaticity change per unit of log-intensity) and the correlation ``ρ = ‖cov(q, ℓ)‖ /
(σ_ℓ σ_q)``. Pixels whose residual is over :data:`OUTLIER` times the window's median do not
enter, so a single edge does not speak for the window. The evidence ramps from 0 to 1 as
``ρ`` rises from :data:`CORRELATION` (sensor noise, uncorrelated between the channels, stays
under it) and as ``β`` rises from ``t_xc``, and it is 0 within :data:`EDGE_RADIUS` px of a
colour edge (as ``t_e`` 0.015 marks one), where the removal's coarse fit would spread a
material's step into ``S_l``'s targets. With ``t_xc > 0`` the texture confidence is
``1 − (1 − c) · evidence``: dense texture that keeps its colour (a same-hue relief, frog
skin, the mortar of a gray wall) stays the shading's, coloured texture goes to the
reflectance. With ``t_xc``, ``τ`` is measured on ``ℓ`` (the mean of the log channels) and
reused as the scale that leaves edge pixels out. So that the marks cost a few percent of a
decomposition, their window statistics (``τ``'s median, the window means) are taken every
``w`` px in each direction (4 for the 9×9 window: two samples per window side) and
interpolated, and the four residuals share one fit in float32.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchiid.core.check import as_mask, check_image, check_shape
from torchiid.core.exceptions import ParameterError
from torchiid.core.local_fit import local_linear_residual, residual_in
from torchiid.priors.shading_terms import edge_confidence, intensity

__all__ = ["REMOVAL_SIGMA", "colour_texture_evidence", "detexture", "texture_confidence"]

#: scale (px) of the local linear fit whose residual :func:`detexture` takes out (the
#: parameter ``t_x_sigma``)
REMOVAL_SIGMA = 5.0

#: correlation of the fine chromaticity and intensity residuals at which the colour evidence
#: starts; it is full 0.3 above (channel noise over the 81-pixel window stays below 0.4)
CORRELATION = 0.5

#: a pixel whose fine residual is over this many times its window's median is an edge or a
#: line, not part of a dense texture, and does not enter the colour statistics
OUTLIER = 3.0

#: no colour evidence within this many px of a colour edge (the removal fit's scale,
#: ``t_x_sigma``'s default)
EDGE_RADIUS = 5

#: the colour-edge deviation of those edges: a constant of the marks, the ``default``'s
#: ``t_e`` (the parameter ``t_e`` does not change it)
EDGE_DEVIATION = 0.015

#: output rows per block of the torch path's window medians, so that its window copies stay
#: small
_MEDIAN_ROWS = 32


def _medians(r: torch.Tensor, window: int, grid: int) -> torch.Tensor:
    """The median over each ``(2w + 1)²`` window of ``r`` at every ``grid``-th pixel.

    ``r`` is ``(B, 1, H, W)``, NaN where a pixel is not part of the windows; a window with
    no such pixel gives 0. Each window's values are copied out (``unfold``), a block of
    output rows at a time.
    """
    b, _, h, w = r.shape
    hs, ws = (h - 1) // grid + 1, (w - 1) // grid + 1
    side = 2 * window + 1
    pad = F.pad(r, (window,) * 4, value=float("nan"))
    rows = []
    for i0 in range(0, hs, _MEDIAN_ROWS):
        i1 = min(hs, i0 + _MEDIAN_ROWS)
        part = pad[..., i0 * grid : (i1 - 1) * grid + side, :]
        cols = F.unfold(part, side, stride=grid).view(b, -1, i1 - i0, ws)
        rows.append(cols.nanmedian(1, keepdim=True).values)
    return torch.cat(rows, -2).nan_to_num(0.0)


def _grid_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """The window mean (zeros outside) at every ``window``-th pixel, as two 1-D passes."""
    k = 2 * window + 1
    x = F.avg_pool2d(x, (k, 1), (window, 1), (window, 0), count_include_pad=True)
    return F.avg_pool2d(x, (1, k), (1, window), (0, window), count_include_pad=True)


def _from_grid(values: torch.Tensor, step: int, h: int, w: int) -> torch.Tensor:
    """Bilinear interpolation of grid values (point ``i`` at pixel ``i·step``) to every pixel."""
    size = ((values.shape[-2] - 1) * step + 1, (values.shape[-1] - 1) * step + 1)
    out = F.interpolate(values, size=size, mode="bilinear", align_corners=True)
    return F.pad(out, (0, w - size[1], 0, h - size[0]), mode="replicate")


def _dilate(x: torch.Tensor, reach: int) -> torch.Tensor:
    """The maximum over each ``(2 reach + 1)²`` square (zeros outside), as shifted maxima.

    ``max_pool2d`` takes several times longer on a CPU than these ``4 reach`` passes.
    """
    h, w = x.shape[-2:]
    pad = F.pad(x, (0, 0, reach, reach))
    y = pad[..., :h, :].clone()
    for i in range(1, 2 * reach + 1):
        torch.maximum(y, pad[..., i : i + h, :], out=y)
    pad = F.pad(y, (reach, reach))
    out = pad[..., :w].clone()
    for i in range(1, 2 * reach + 1):
        torch.maximum(out, pad[..., i : i + w], out=out)
    return out


def _check(t_x: float, t_xc: float, window: int) -> None:
    if not t_x > 0 or not window > 0:
        raise ParameterError(f"t_x and window must be > 0, got t_x={t_x}, window={window}")
    if not t_xc >= 0:
        raise ParameterError(f"t_xc must be >= 0, got {t_xc}")


def _colour_marks(
    image: torch.Tensor,
    t_xc: float,
    mask: torch.Tensor | None,
    dark_eps: float,
    window: int,
    t_e: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(τ, evidence)``: the window median of ``|r_ℓ|`` and the colour evidence."""
    mask = None if mask is None else as_mask(mask, image, "mask")
    # ℓ along (1, 1, 1) in log-RGB and q orthogonal to it: light of one colour moves only ℓ
    log_rgb = image.float().clamp_min(dark_eps).log()
    ell = log_rgb.mean(1, keepdim=True)
    q = log_rgb - ell
    r = residual_in(torch.cat([ell, q], 1), mask, 1.0, torch.float32)
    r_ell, r_q = r[:, :1], r[:, 1:]
    h, w = r.shape[-2:]
    size = r_ell.abs()
    inside = None if mask is None else as_mask(mask, r_ell, "mask")
    seen = size if inside is None else torch.where(inside, size, torch.nan)
    tau = _from_grid(_medians(seen, window, window), window, h, w)
    keep = size <= OUTLIER * tau.clamp_min(1e-6)
    keep = (keep if inside is None else keep & inside).float()
    kept = keep * r_ell
    terms = [keep, kept * r_ell, keep * r_q.square().sum(1, keepdim=True), r_q * kept]
    sums = _grid_mean(torch.cat(terms, 1), window)
    n = sums[:, :1].clamp_min(1e-12)
    var_ell, var_q = sums[:, 1:2] / n, sums[:, 2:3] / n
    cov = ((sums[:, 3:] / n) ** 2).sum(1, keepdim=True).sqrt()
    slope = cov / var_ell.clamp_min(1e-12)
    corr = cov / (var_ell * var_q).sqrt().clamp_min(1e-12)
    ramp = ((corr - CORRELATION) / 0.3).clamp(0, 1) * ((slope - t_xc) / (2 * t_xc)).clamp(0, 1)
    evidence = _from_grid(ramp, window, h, w)
    edges = (edge_confidence(image.float(), t_e, dark_eps, mask) < 0.5).float()
    evidence = evidence * (1 - _dilate(edges, EDGE_RADIUS))
    return tau, evidence if inside is None else evidence * inside


def texture_confidence(
    image: torch.Tensor,
    t_x: float,
    mask: torch.Tensor | None = None,
    dark_eps: float = 1e-4,
    window: int = 4,
    t_xc: float = 0.0,
) -> torch.Tensor:
    """``exp(−τ²/t_x²)``: 1 away from fine texture, near 0 inside it (see the module notes).

    Args:
        image: ``(B, 3, H, W)`` linear RGB.
        t_x: texture deviation, in log-intensity (RMS of the fine-scale residual).
        mask: optional ``(B, 1, H, W)`` bool; only pixels inside enter the fits and means.
        dark_eps: intensity floor before the log.
        window: half-side ``w`` (px) of the median's square window.
        t_xc: with ``> 0``, only texture that changes colour with its lightness counts:
            ``1 − (1 − c) ·`` :func:`colour_texture_evidence`, ``τ`` measured on the mean
            of the log channels every ``window`` px and interpolated (0: all dense
            texture, ``τ`` on the log of the mean intensity at every pixel).

    Returns:
        ``(B, 1, H, W)`` in the image's dtype.
    """
    check_image(image, "image", channels=3)
    _check(t_x, t_xc, window)
    mask = None if mask is None else as_mask(mask, image, "mask")
    if t_xc > 0:
        tau, evidence = _colour_marks(image, t_xc, mask, dark_eps, window, EDGE_DEVIATION)
        c = 1 - (1 - torch.exp(-((tau / t_x) ** 2))) * evidence
        return c.to(image.dtype)
    r = local_linear_residual(intensity(image, dark_eps).log(), mask, sigma=1.0).abs()
    if mask is not None:
        r = torch.where(as_mask(mask, r), r, torch.nan)  # outside pixels take no part
    tau = _medians(r, window, 1)
    return torch.exp(-((tau / t_x) ** 2)).to(image.dtype)


def colour_texture_evidence(
    image: torch.Tensor,
    t_xc: float,
    mask: torch.Tensor | None = None,
    dark_eps: float = 1e-4,
    window: int = 4,
    t_e: float = EDGE_DEVIATION,
) -> torch.Tensor:
    """How sure each pixel's fine texture changes colour with its lightness (module notes).

    Args:
        image: ``(B, 3, H, W)`` linear RGB.
        t_xc: the slope ``β`` (log-chromaticity per unit of log-intensity) at which the
            evidence starts; it is full at ``3·t_xc``.
        mask: optional ``(B, 1, H, W)`` bool; only pixels inside enter.
        dark_eps: intensity floor before the log.
        window: half-side (px) of the statistics' square window.
        t_e: the colour-edge deviation of the edge marks whose surroundings get none.

    Returns:
        ``(B, 1, H, W)`` float32 in ``[0, 1]``.
    """
    check_image(image, "image", channels=3)
    if not t_xc > 0 or not window > 0:
        raise ParameterError(f"t_xc and window must be > 0, got t_xc={t_xc}, window={window}")
    return _colour_marks(image, t_xc, mask, dark_eps, window, t_e)[1]


def detexture(
    image: torch.Tensor,
    t_x: float,
    mask: torch.Tensor | None = None,
    dark_eps: float = 1e-4,
    sigma: float = REMOVAL_SIGMA,
    t_xc: float = 0.0,
    confidence: torch.Tensor | None = None,
) -> torch.Tensor:
    """``image`` without its fine texture where :func:`texture_confidence` finds it dense.

    ``confidence``, if given, is that confidence made beforehand (``(B, 1, H, W)``): a
    coarse copy of an image takes its working resolution's confidence, area-averaged, since
    the 1-px detection sees a different texture at every scale.

    Returns:
        ``(B, 3, H, W)``: ``image · exp(−(1 − c) · r')`` with ``c`` the texture confidence and
        ``r'`` the residual of ``log p`` after its local linear fit at ``sigma`` px (in
        float32), in the image's dtype (float32 at least).
    """
    if confidence is None:
        c = texture_confidence(image, t_x, mask, dark_eps, t_xc=t_xc)
    else:
        check_image(image, "image", channels=3)
        shape = (image.shape[0], 1, *image.shape[-2:])
        check_shape(confidence, shape, "confidence (ShadingProblem.texture)")
        c = confidence
    r = residual_in(intensity(image, dark_eps).log(), mask, sigma, torch.float32)
    dtype = torch.promote_types(image.dtype, torch.float32)
    return (image.to(dtype) * torch.exp((c.to(dtype) - 1) * r)).to(image.dtype)
