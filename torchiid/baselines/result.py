"""The result type shared by the baselines: a reflectance and a shading layer."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["BaselineResult"]


@dataclass(frozen=True, eq=False)
class BaselineResult:
    """Layers of a baseline decomposition, **linear**, in the convention of ``decompose``.

    Attributes:
        reflectance: ``(B, 3, H, W)`` reflectance.
        shading: ``(B, 1, H, W)`` gray shading.
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
