"""Illumination colour: tint the light near the brightest (directly lit) regions."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import torch
from torch import nn

from torchiid.core.bands import by_rows
from torchiid.core.stats import image_quantile
from torchiid.edit.colour import colour_ab, lab_to_linear, linear_to_lab
from torchiid.edit.common import check_edit_numbers, check_layers, white_level

__all__ = ["IlluminationColour", "illumination_colour", "light_weights"]


def _distance_to_nearest_zero(mask: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance (float32, px) from each pixel of ``mask`` to its nearest 0.

    OpenCV's exact transform runs without Intel IPP here: IPP's version of it returns some
    distances one float32 step above the correctly rounded value, and which ones changes from
    one call to the next, so the same shading would not always give the same weights.
    OpenCV's own code gives the correctly rounded distance on every call, as fast.
    ``cv2.ipp.setUseIPP`` applies to the calling thread only, so other threads keep IPP.
    """
    use_ipp = cv2.ipp.useIPP()
    cv2.ipp.setUseIPP(False)
    try:
        return cv2.distanceTransform(mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    finally:
        cv2.ipp.setUseIPP(use_ipp)


def light_weights(
    shading: torch.Tensor, percentile: float = 0.95, radius: float = 0.35
) -> torch.Tensor:
    """``(B, 1, H, W)`` weights: 1 on the light regions, falling to 0 at ``radius``.

    The light regions are the pixels whose shading luminance is at least its ``percentile``
    quantile; a pixel at distance ``d`` from the nearest of them gets ``1 - smoothstep(d / r)``
    with ``r = radius · longer side``, so pixels farther than ``r`` get exactly 0. ``d`` is the
    exact Euclidean distance, the same on every call for the same shading.
    """
    check_edit_numbers(shading, percentile=percentile, radius=radius)
    y = shading.mean(1, keepdim=True)
    q = image_quantile(y, percentile).view(-1, 1, 1, 1).to(y)
    light = (y >= q).cpu().numpy()
    r = radius * max(shading.shape[-2:])
    out = np.empty(light.shape, np.float32)
    for b in range(light.shape[0]):
        d = _distance_to_nearest_zero((~light[b, 0]).astype(np.uint8))
        t = np.clip(d / r, 0, 1)
        out[b, 0] = 1 - t * t * (3 - 2 * t)
    return torch.from_numpy(out).to(shading)


def illumination_colour(
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    tint: str | Sequence[float] = "red",
    strength: float = 1.0,
    *,
    percentile: float = 0.95,
    radius: float = 0.35,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Change the colour of the light near the light-source regions.

    The shading (normalised by its 99th percentile) goes to CIELab; its ``a*, b*`` are moved by
    ``strength`` times the tint's ``a*, b*`` (lightness kept) and the edited shading is blended
    with the original by :func:`light_weights` (1 on the pixels in the ``percentile`` quantile
    of the shading, 0 beyond ``radius`` × the longer side, where nothing changes).

    Args:
        reflectance: ``(B, 3, H, W)`` (the merged reflectance of
            :func:`~torchiid.edit.merging.merge`, or ``R``).
        shading: ``(B, 1|3, H, W)`` (the merged shading, or ``S``).
        tint: a colour for :func:`~torchiid.edit.colour.parse_colour` (``"red"``, ``"green"``,
            ``"1,0.5,0"``, ...).
        strength: how much of the tint's chroma is added (0: none, 1: the tint's own).
        percentile: the light regions' quantile of the shading.
        radius: fall-off distance as a fraction of the longer side.

    Returns:
        ``(edited image, edited shading)``, both ``(B, 3, H, W)``.
    """
    check_layers(reflectance, shading)
    check_edit_numbers(shading, strength=strength)
    tint_ab = colour_ab(tint, shading)
    s3 = shading.expand(-1, 3, -1, -1)
    white = white_level(s3)
    shift = torch.cat([torch.zeros_like(tint_ab[:, :1]), tint_ab], 1) * strength
    w = light_weights(shading, percentile, radius)

    def tinted(s3: torch.Tensor, w: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, ...]:
        full = lab_to_linear(linear_to_lab(s3 / white) + shift).clamp_min(0) * white
        new_s = s3 + w * (full - s3)
        return r * new_s, new_s

    return by_rows(tinted, s3, w, reflectance)


class IlluminationColour(nn.Module):
    """:func:`illumination_colour` as a module; ``forward(R, S)`` returns ``(image, shading)``."""

    def __init__(self, tint="red", strength: float = 1.0, percentile=0.95, radius=0.35) -> None:
        super().__init__()
        self.tint, self.strength, self.percentile, self.radius = tint, strength, percentile, radius

    def forward(self, reflectance, shading):  # noqa: D102
        return illumination_colour(
            reflectance,
            shading,
            self.tint,
            self.strength,
            percentile=self.percentile,
            radius=self.radius,
        )
