"""Shadow softening: compress (or expand) the log-shading's range around a pivot."""

from __future__ import annotations

import torch
from torch import nn

from torchiid.core.bands import by_rows
from torchiid.core.exceptions import ParameterError
from torchiid.edit.common import (
    EPS,
    check_edit_numbers,
    check_layers,
    gaussian,
    region,
    white_level,
)

__all__ = ["SoftenShadows", "soften_shadows"]


def soften_shadows(
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    amount: float = 0.5,
    *,
    mask: torch.Tensor | None = None,
    pivot: float = 0.99,
    feather: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Compress (soften) or expand (harden) the log-shading's range.

    ``log S' = log p + (1 − amount) · (log S − log p)`` with ``p`` the shading luminance's
    ``pivot`` quantile: shading at ``p`` stays, darker shading (shadows) is lifted towards it
    for ``0 < amount <= 1`` (1: flat shading) and deepened for ``amount < 0``. The shading's
    colour (a coloured merged shading) is kept: the factor ``S' / S`` is gray.

    Args:
        reflectance: ``(B, 3, H, W)``.
        shading: ``(B, 1|3, H, W)``.
        amount: in [-10, 1]; 0 changes nothing.
        mask: ``(B, 1, H, W)`` bool: edit only there (default: everywhere).
        pivot: the quantile that stays where it is.
        feather: σ in pixels of a Gaussian blur of the mask's edge (0: hard edge).

    Returns:
        ``(edited image, edited shading)``.
    """
    check_layers(reflectance, shading)
    check_edit_numbers(reflectance, amount=amount, feather=feather)
    if not 0 < pivot <= 1:
        raise ParameterError(f"pivot must be in (0, 1], got {pivot}")
    p = white_level(shading, pivot)
    w = None
    if mask is not None:
        w = region(mask, reflectance).to(shading.dtype)
        if feather > 0:
            w = gaussian(w, feather)

    def softened(
        r: torch.Tensor, s: torch.Tensor, *w: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        y = s.mean(1, keepdim=True).clamp_min(EPS)
        factor = torch.exp(-amount * (y.log() - p.log()))
        if w:
            factor = 1 + w[0] * (factor - 1)
        new_s = s * factor
        return r * new_s, new_s

    return by_rows(softened, reflectance, shading, *(() if w is None else (w,)))


class SoftenShadows(nn.Module):
    """:func:`soften_shadows` as a module; ``forward(R, S, mask=None)``."""

    def __init__(self, amount: float = 0.5, pivot: float = 0.99, feather: float = 0.0) -> None:
        super().__init__()
        self.amount, self.pivot, self.feather = amount, pivot, feather

    def forward(self, reflectance, shading, mask=None):  # noqa: D102
        return soften_shadows(
            reflectance, shading, self.amount, mask=mask, pivot=self.pivot, feather=self.feather
        )
