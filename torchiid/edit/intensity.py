"""Illumination intensity: raise indirectly lit regions, keep directly lit ones."""

from __future__ import annotations

import torch
from torch import nn

from torchiid.core.bands import by_rows
from torchiid.core.exceptions import ParameterError
from torchiid.edit.common import (
    EPS,
    check_edit_numbers,
    check_layers,
    default_blur,
    gaussian,
    safe_div,
    white_level,
)
from torchiid.edit.merging import Merged, merge

__all__ = ["COMBINE", "IlluminationIntensity", "illumination_intensity"]

#: how :func:`illumination_intensity` combines its two light estimates
COMBINE = ("mean", "e1", "e2", "max")


def illumination_intensity(
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    sigma: torch.Tensor,
    rho: torch.Tensor,
    strength: float = 0.5,
    *,
    combine: str = "mean",
    blur: float | None = None,
    merged: Merged | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Raise indirectly lit regions, keep directly lit ones ("single image LDR to HDR").

    ``E1 = mean(ρ − R, S − σ)`` (additive) and ``E2 = mean(ρ / R, S / σ)`` (multiplicative)
    measure the light one stage sees and the other misses. Each is turned into a non-negative
    light estimate in shading units and Gaussian-filtered: ``L1 = G * |E1|`` (luminance of),
    ``L2 = G * |E2 − 1| · S_m`` (``S_m`` the merged shading's luminance). ``combine`` picks
    ``L1`` (``"e1"``), ``L2`` (``"e2"``), their mean (``"mean"``, the default: both are
    estimates of the same missing light, so neither is preferred) or their maximum (``"max"``).
    ``L`` is normalised by its maximum, so ``strength`` means the same on every image, and added
    to the merged shading as ``S' = S_m + strength · white · L̂ · (1 − S_m / white)²₊``, where
    ``white`` is the merged shading's 99th percentile: the added light fades to 0 where the
    shading reaches the directly lit level, so the brightest pixels do not change and no
    rescaling of the display range is needed (the result stays within the input's range
    except where ``S_m`` is just below ``white``, by at most ``strength · 4/27 · white``).
    The result is ``R_m · S'``.

    Args:
        image: ``(B, 3, H, W)`` linear ``I``.
        reflectance: Stage 2 ``R``.
        shading: Stage 2 ``S``.
        sigma: Stage 1 ``σ``.
        rho: Stage 1 ``ρ``.
        strength: how much light is added (0: none; >= 0).
        combine: ``"mean"``, ``"e1"``, ``"e2"`` or ``"max"``.
        blur: σ in pixels of the filter (default: 4 ×
            :func:`~torchiid.edit.common.default_blur`).
        merged: the :func:`~torchiid.edit.merging.merge` of these layers if already computed.

    Returns:
        ``(edited image, edited shading)``, both ``(B, 3, H, W)``.
    """
    if combine not in COMBINE:
        raise ParameterError(f"combine must be one of {', '.join(COMBINE)}, got {combine!r}")
    check_layers(image, reflectance, shading, sigma, rho)
    check_edit_numbers(image, strength=strength, intensity=True, blur=blur)
    if merged is None:
        merged = merge(image, reflectance, shading, sigma, rho)
    if blur is None:
        blur = 4 * default_blur(*image.shape[-2:])
    e1, e2, sm = by_rows(_estimates, reflectance, shading, sigma, rho, merged.shading)
    l1 = gaussian(e1, blur)
    l2 = gaussian(e2, blur)
    light = {"e1": l1, "e2": l2, "mean": (l1 + l2) / 2, "max": torch.maximum(l1, l2)}[combine]
    peak = light.flatten(1).amax(1).clamp_min(EPS).view(-1, 1, 1, 1)
    white = white_level(merged.shading)

    def lit(
        light: torch.Tensor, sm: torch.Tensor, ms: torch.Tensor, mr: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        fade = (1 - sm / white).clamp_min(0) ** 2
        new_s = ms + strength * white * (light / peak) * fade
        return mr * new_s, new_s

    return by_rows(lit, light, sm, merged.shading, merged.reflectance)


def _estimates(
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    sigma: torch.Tensor,
    rho: torch.Tensor,
    merged_shading: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``|E1|`` and ``|E2 − 1| · S_m`` before the filter, and ``S_m``, per pixel."""
    e1 = ((rho - reflectance) + (shading - sigma)) / 2
    e2 = (safe_div(rho, reflectance) + safe_div(shading, sigma)) / 2
    sm = merged_shading.mean(1, keepdim=True)
    return e1.abs().mean(1, keepdim=True), (e2 - 1).abs().mean(1, keepdim=True) * sm, sm


class IlluminationIntensity(nn.Module):
    """:func:`illumination_intensity` as a module; ``forward(I, R, S, σ, ρ)``."""

    def __init__(self, strength=0.5, combine="mean", blur: float | None = None) -> None:
        super().__init__()
        self.strength, self.combine, self.blur = strength, combine, blur

    def forward(self, image, reflectance, shading, sigma, rho):  # noqa: D102
        return illumination_intensity(
            image,
            reflectance,
            shading,
            sigma,
            rho,
            self.strength,
            combine=self.combine,
            blur=self.blur,
        )
