"""The merged components of the two stages, the step the paper's applications start from."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from torchiid.core.bands import by_rows
from torchiid.edit.common import (
    EPS,
    check_edit_numbers,
    check_layers,
    default_blur,
    gaussian,
    safe_div,
)

__all__ = ["Merge", "Merged", "merge"]


@dataclass(frozen=True)
class Merged:
    """The merged components (:func:`merge`), every tensor ``(B, 3, H, W)`` linear.

    Attributes:
        reflectance: merged reflectance ``I / shading``.
        shading: merged shading ``mean(S / C, σ · C)`` (coloured where ``C`` is).
        c: the Gaussian-filtered mean of ``C1`` and ``C2`` (the "illumination colour").
        c1: ``I / I_Rσ``.
        c2: ``I / I_ρS``.
        sparse: ``I_Rσ = R · σ`` (the sparse reconstruction).
        detailed: ``I_ρS = ρ · S`` (the detailed reconstruction).
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
    c: torch.Tensor
    c1: torch.Tensor
    c2: torch.Tensor
    sparse: torch.Tensor
    detailed: torch.Tensor


def merge(
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    sigma: torch.Tensor,
    rho: torch.Tensor,
    *,
    blur: float | None = None,
) -> Merged:
    """Merge the two stages' layers (the paper's § Applications).

    ``I_Rσ = R · σ`` and ``I_ρS = ρ · S`` reconstruct the image from Stage 2's reflectance with
    Stage 1's shading and vice versa; the fractional residues ``C1 = I / I_Rσ`` and
    ``C2 = I / I_ρS`` are averaged and Gaussian-filtered into ``C``; the merged shading is
    ``mean(S / C, σ · C)`` and the merged reflectance ``I / merged shading``. Where a
    denominator is 0 (outside a decomposition's mask) the residue is taken as 1.

    What ``C`` carries here: in this implementation both stages reconstruct the image
    (``R · S = I`` inside the mask, ``ρ = I / σ`` up to ρ's clipping to ``[0, 1]``) and both
    shadings are **gray**, so ``C1 ≈ S / σ``, ``C2 ≈ σ / S`` and ``C ≈ G * (S/σ + σ/S) / 2``:
    a **gray** factor ``>= 1`` that measures how much the two stages' shadings disagree
    (``1 + (log S/σ)² / 2`` to second order), not a colour. It is coloured only where the
    reconstructions are inexact (ρ clipped at 1, the 16-bit quantisation of a saved ``R``, dark
    or clipped pixels), and only there does the merged shading pick up a colour. The merged
    shading lies between the two shadings: ``S / C`` pulls ``S`` towards the smoother σ-side
    where they disagree, ``σ · C`` pushes σ back up; with ``σ = S`` (or ``ρ = R``) the merge is
    the identity.

    Args:
        image: ``(B, 3, H, W)`` linear image ``I``.
        reflectance: ``(B, 3, H, W)`` Stage 2 reflectance ``R``.
        shading: ``(B, 1|3, H, W)`` Stage 2 shading ``S``.
        sigma: ``(B, 1|3, H, W)`` last Stage 1 shading ``σ``.
        rho: ``(B, 3, H, W)`` last Stage 1 reflectance ``ρ``.
        blur: σ in pixels of the Gaussian filter of ``C`` (the paper gives none); default
            :func:`~torchiid.edit.common.default_blur`, 1% of the longer side: it removes pixel
            noise and the quantisation of saved layers but keeps the residue's structure at
            object scale.

    Returns:
        :class:`Merged`.
    """
    check_layers(image, reflectance, shading, sigma, rho)
    check_edit_numbers(image, blur=blur)
    if blur is None:
        blur = default_blur(*image.shape[-2:])
    sparse, detailed, c1, c2, mean_c = by_rows(_residues, image, reflectance, shading, sigma, rho)
    c = gaussian(mean_c, blur).clamp_min(EPS)
    merged_r, merged_s = by_rows(_merged, image, shading, sigma, c)
    return Merged(merged_r, merged_s, c, c1, c2, sparse, detailed)


def _residues(
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    sigma: torch.Tensor,
    rho: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    """``R · σ``, ``ρ · S``, ``C1``, ``C2`` and their mean, per pixel."""
    sparse = reflectance * sigma
    detailed = rho * shading
    c1 = safe_div(image, sparse)
    c2 = safe_div(image, detailed)
    return sparse, detailed, c1, c2, (c1 + c2) / 2


def _merged(
    image: torch.Tensor, shading: torch.Tensor, sigma: torch.Tensor, c: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The merged reflectance and shading, per pixel."""
    merged_s = (shading / c + sigma * c) / 2
    return safe_div(image, merged_s, 0.0), merged_s


class Merge(nn.Module):
    """:func:`merge` as a module; ``forward(image, R, S, σ, ρ)`` returns :class:`Merged`."""

    def __init__(self, blur: float | None = None) -> None:
        super().__init__()
        self.blur = blur

    def forward(self, image, reflectance, shading, sigma, rho) -> Merged:  # noqa: D102
        return merge(image, reflectance, shading, sigma, rho, blur=self.blur)
