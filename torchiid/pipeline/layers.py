"""The output layers: the shading brought back to the input's resolution, ``R = I / S``.

Scale: the product ``R · S`` is ambiguous up to a factor. The reflectance is returned as an
albedo in ``[0, 1]``: its ``albedo_quantile`` (0.999) quantile of the per-pixel maximum channel
is 1, and the few pixels above have their excess moved into the shading, which is gray, carries
the rest and may exceed 1 (see :func:`full_resolution_layers`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchiid.core.stats import image_quantile, subgrid
from torchiid.params import OutputParameters, Parameters
from torchiid.pipeline.inputs import WorkingInputs
from torchiid.pipeline.results import IterationLayers
from torchiid.priors.shading_terms import pixel_confidence
from torchiid.resample import GuidedUpsampler, downsample, row_bands

__all__ = [
    "FullLayers",
    "full_resolution_layers",
    "OutputLayers",
    "output_layers",
    "gray_shading",
    "final_shading",
    "log_luminance",
    "normalised_iteration",
]


@dataclass(frozen=True)
class FullLayers:
    """Full-resolution layers of one shading estimate (see :func:`full_resolution_layers`).

    Attributes:
        reflectance: ``(B, 3, H, W)`` albedo in ``[0, 1]``, 0 outside the mask.
        shading: ``(B, 1, H, W)`` gray shading (may exceed 1), 0 outside the mask.
        shading_white: ``(B,)`` the shading's ``params.output.view_quantile`` quantile inside the
            mask: the value shown as white in the viewable shading.
        albedo_excess: ``(B,)`` fraction of the pixels (inside the mask) whose reflectance
            exceeded 1 after the global scale and had the excess moved into the shading.
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
    shading_white: torch.Tensor
    albedo_excess: torch.Tensor


def full_resolution_layers(
    image: torch.Tensor,
    shading_low: torch.Tensor,
    guide_low: torch.Tensor | None,
    mask: torch.Tensor | None,
    params: Parameters,
) -> FullLayers:
    """Full-resolution ``(R, S)`` from a shading solved at the working resolution.

    1. ``log S`` is upsampled by guided filtering with the full-resolution log-luminance as
       guide (:class:`~torchiid.resample.GuidedUpsampler`), band by band; at the working
       resolution itself it is used as it is.
    2. ``R = I / S``, so the reflectance keeps every full-resolution detail of the photo.
    3. **Scale convention** (``R · S`` is ambiguous up to a factor): the global factor makes
       the ``params.output.albedo_quantile`` quantile (default 0.999) of ``max_c R_c`` inside the
       mask equal to 1 — reflectance is an albedo in ``[0, 1]`` and the shading carries the
       rest (it may exceed 1: it is high dynamic range by nature). The few pixels above that
       quantile (specular highlights, light sources, noise in the dark) keep ``R ≤ 1`` by
       moving their excess ``max_c R_c`` into the shading, so ``R · S == I`` still holds
       exactly. A quantile rather than the maximum keeps one outlier from darkening the
       whole albedo.

    Args:
        image: ``(B, 3, H, W)`` full-resolution linear RGB.
        shading_low: ``(B, 1, h, w)`` positive shading at the working resolution.
        guide_low: ``(B, 1, h, w)`` log-luminance of the working-resolution image (unused,
            may be ``None``, when ``shading_low`` is at full resolution).
        mask: ``(B, 1, H, W)`` bool or ``None``; outside it both layers are 0.
        params: supplies ``params.output`` (the guided filter's ``guide_radius`` /
            ``guide_eps``, ``albedo_quantile``, ``view_quantile``), ``dark_eps`` and
            ``shading_floor``.

    Returns:
        :class:`FullLayers`.
    """
    b, _, big_h, big_w = image.shape
    floor, out = params.reflectance.shading_floor, params.output
    log_low = shading_low.clamp_min(floor).log()
    shading = image.new_empty(b, 1, big_h, big_w)
    if tuple(log_low.shape[-2:]) == (big_h, big_w):
        torch.exp(log_low, out=shading)
    else:
        weight = None
        if mask is not None:  # the outside (blacked out, shading 1) must not enter the fits
            weight = downsample(mask.to(image.dtype), tuple(log_low.shape[-2:]))
        up = GuidedUpsampler(
            log_low, guide_low, (big_h, big_w), out.guide_radius, out.guide_eps, weight
        )
        for rows in row_bands(big_h, big_w):
            band = up.band(rows, log_luminance(image[:, :, rows], params.shading.dark_eps))
            shading[:, :, rows] = band.exp_()
    shading.clamp_min_(floor)
    return _albedo_scale(image, shading, mask, out)


def _albedo_scale(
    image: torch.Tensor, shading: torch.Tensor, mask: torch.Tensor | None, out: OutputParameters
) -> FullLayers:
    """Steps 2 and 3 of :func:`full_resolution_layers`: ``R = I / S``, an albedo in [0, 1]."""
    b, _, big_h, big_w = image.shape
    # global scale from a sub-grid (about a megapixel is plenty for a quantile)
    img_s, step = subgrid(image)
    peak_s = (img_s / shading[..., ::step, ::step]).amax(1, keepdim=True)
    msk_s = None if mask is None else mask[..., ::step, ::step]
    # "higher": at most a 1 - albedo_quantile share of the (sub-grid) pixels lies above k
    k = image_quantile(peak_s, out.albedo_quantile, msk_s, interpolation="higher")
    k = torch.where(k > 1e-12, k, torch.ones_like(k)).view(b, 1, 1, 1)  # black image: R = 0
    reflectance = image.new_empty(b, 3, big_h, big_w)
    moved = torch.zeros(b, device=image.device, dtype=torch.float64)
    for rows in row_bands(big_h, big_w):
        s_band = shading[:, :, rows].mul_(k)
        i_band = image[:, :, rows]
        excess = (i_band / s_band).amax(1, keepdim=True)
        over = excess > 1
        if mask is not None:
            over &= mask[:, :, rows]
        moved += over.flatten(1).sum(1)
        s_band.mul_(excess.clamp_min_(1))
        torch.div(i_band, s_band, out=reflectance[:, :, rows])
        reflectance[:, :, rows].clamp_(0, 1)  # R <= 1 already; removes 1 + 1 ulp
    if mask is not None:
        keep = mask.to(image.dtype)
        shading.mul_(keep)
        reflectance.mul_(keep)
        area = mask.flatten(1).sum(1).to(torch.float64)
    else:
        area = torch.full((b,), float(big_h * big_w), dtype=torch.float64, device=image.device)
    shade_s = shading[..., ::step, ::step]
    white = image_quantile(shade_s, out.view_quantile, msk_s)
    white = torch.where(white > 0, white, torch.ones_like(white))
    return FullLayers(reflectance, shading, white, (moved / area).to(torch.float32))


def gray_shading(image: torch.Tensor, refl: torch.Tensor, floor: float) -> torch.Tensor:
    """Gray ``S = Σ_c I_c / Σ_c R_c`` (the least-squares-like gray ratio), floored."""
    s = image.sum(1, keepdim=True) / refl.sum(1, keepdim=True).clamp_min(floor)
    return s.clamp_min(floor)


def final_shading(
    img: torch.Tensor, refl: torch.Tensor, sigma: torch.Tensor, params: Parameters
) -> torch.Tensor:
    """The working-resolution shading of the output: Stage 2's ``I / R`` where it is informed.

    In a dark pixel ``I ≈ 0``, so ``I / R`` is ≈ 0 whatever the light there: the shading
    would show every black object as an unlit hole. Where the pixel confidence ``c``
    (:func:`~torchiid.priors.shading_terms.pixel_confidence`) is below 1 the log-shading is
    blended toward Stage 1's ``σ``, which the confidence-aware ``S_l`` made a smooth
    continuation of the surroundings there: ``log S = c·log(I / R) + (1 − c)·log σ``.
    """
    floor, sh = params.reflectance.shading_floor, params.shading
    s2 = gray_shading(img, refl, floor)
    if sh.dark_level <= 0 and sh.clip_level <= 0:
        return s2
    c = pixel_confidence(img, sh.dark_level, sh.clip_level)
    if bool((c >= 1).all()):
        return s2
    log_s = c * s2.log() + (1 - c) * sigma.clamp_min(floor).log()
    return log_s.exp()


def log_luminance(image: torch.Tensor, eps: float) -> torch.Tensor:
    """``log Y`` (Rec. 709 luminance of linear RGB), clamped to ``eps``: the guide."""
    y = 0.2126 * image[:, :1] + 0.7152 * image[:, 1:2] + 0.0722 * image[:, 2:3]
    return y.clamp_min(eps).log()


def normalised_iteration(
    img: torch.Tensor, it: IterationLayers, msk: torch.Tensor | None, params: Parameters
) -> IterationLayers:
    """An alternation's layers in the output convention (albedos in [0, 1])."""
    guide = log_luminance(img, params.shading.dark_eps)
    st1 = full_resolution_layers(img, it.sigma, guide, msk, params)
    st2 = full_resolution_layers(img, it.shading, guide, msk, params)
    return IterationLayers(
        sigma=st1.shading, rho=st1.reflectance, reflectance=st2.reflectance, shading=st2.shading
    )


@dataclass(frozen=True)
class OutputLayers:
    """The layers :func:`~torchiid.model.decompose` returns, in float at the input's size.

    Attributes:
        final: the final ``R, S`` (Stage 2's, with Stage 1's σ where pixels are dark).
        stage1: the last Stage 1 layers ``σ, ρ``, or ``None``.
        iterations: every alternation's layers in the output convention (or none).
    """

    final: FullLayers
    stage1: FullLayers | None
    iterations: list[IterationLayers]


def output_layers(
    work: WorkingInputs,
    refl: torch.Tensor,
    sigma: torch.Tensor,
    iterations: list[IterationLayers],
    params: Parameters,
    return_stage1: bool,
) -> OutputLayers:
    """The last alternation's layers at the input's resolution, ``R`` an albedo in [0, 1]."""
    guide_low = log_luminance(work.image, params.shading.dark_eps)
    shading = final_shading(work.image, refl, sigma, params)
    final = full_resolution_layers(work.full, shading, guide_low, work.full_mask, params)
    stage1 = None
    if return_stage1:
        stage1 = full_resolution_layers(work.full, sigma, guide_low, work.full_mask, params)
    kept = [normalised_iteration(work.image, it, work.mask, params) for it in iterations]
    return OutputLayers(final, stage1, kept)
