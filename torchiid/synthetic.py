"""Synthetic intrinsic images with known ground truth, for tests and demos.

:func:`mondrian` draws a piecewise-constant ("Mondrian") reflectance of axis-aligned coloured
rectangles and multiplies it by a smooth shading (a lit, bumpy surface), all in linear RGB.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["SyntheticImage", "mondrian"]


@dataclass(frozen=True)
class SyntheticImage:
    """An image with its ground-truth layers, all linear RGB, ``image == reflectance * shading``.

    Attributes:
        image: ``(B, 3, H, W)``.
        reflectance: ``(B, 3, H, W)`` piecewise constant, values in ``[0.1, 0.9]``.
        shading: ``(B, 1, H, W)`` smooth, values in ``[shading_min, 1]``.
        labels: ``(B, H, W)`` long, the rectangle index of every pixel.
    """

    image: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor
    labels: torch.Tensor


def mondrian(
    height: int = 64,
    width: int = 64,
    batch: int = 1,
    patches: int = 12,
    shading_min: float = 0.2,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> SyntheticImage:
    """Random Mondrian reflectance times smooth shading.

    Args:
        height: image height.
        width: image width.
        batch: number of images ``B`` (each drawn independently).
        patches: number of rectangles drawn over a background.
        shading_min: darkest shading value.
        seed: seed of a private generator (the global RNG is untouched).
        dtype: floating dtype of the outputs.
        device: device of the outputs.

    Returns:
        :class:`SyntheticImage`.

    Shape:
        image ``(B, 3, H, W)``, reflectance ``(B, 3, H, W)``, shading ``(B, 1, H, W)``.

    >>> s = mondrian(32, 48, batch=2)
    >>> s.image.shape, bool(torch.allclose(s.image, s.reflectance * s.shading))
    (torch.Size([2, 3, 32, 48]), True)
    """
    g = torch.Generator().manual_seed(seed)
    refl = torch.empty(batch, 3, height, width, dtype=torch.float64)
    labels = torch.zeros(batch, height, width, dtype=torch.long)
    yy = torch.linspace(-1, 1, height, dtype=torch.float64).view(-1, 1)
    xx = torch.linspace(-1, 1, width, dtype=torch.float64).view(1, -1)
    shading = torch.empty(batch, 1, height, width, dtype=torch.float64)
    for b in range(batch):
        colours = 0.1 + 0.8 * torch.rand(patches + 1, 3, generator=g, dtype=torch.float64)
        for p in range(1, patches + 1):
            y0, x0 = (torch.rand(2, generator=g) * torch.tensor([height, width]) * 0.8).long()
            hh = int(height * (0.15 + 0.35 * float(torch.rand(1, generator=g))))
            ww = int(width * (0.15 + 0.35 * float(torch.rand(1, generator=g))))
            labels[b, y0 : y0 + hh, x0 : x0 + ww] = p
        refl[b] = colours[labels[b]].permute(2, 0, 1)
        # a lit bumpy surface: light direction plus a few smooth bumps
        lx, ly = (torch.rand(2, generator=g, dtype=torch.float64) - 0.5) * 2
        phase = torch.rand(2, generator=g, dtype=torch.float64) * 6.28
        s = 0.6 + 0.25 * (lx * xx + ly * yy)
        s = s + 0.15 * torch.sin(2.5 * xx + phase[0]) * torch.cos(2.0 * yy + phase[1])
        s = (s - s.min()) / (s.max() - s.min())
        shading[b, 0] = shading_min + (1 - shading_min) * s
    image = refl * shading
    return SyntheticImage(
        image=image.to(dtype=dtype, device=device),
        reflectance=refl.to(dtype=dtype, device=device),
        shading=shading.to(dtype=dtype, device=device),
        labels=labels.to(device=device),
    )
