"""Synthetic intrinsic images with known ground truth, for tests and demos.

:func:`mondrian` draws a piecewise-constant ("Mondrian") reflectance of axis-aligned coloured
rectangles and multiplies it by a smooth shading (a lit, bumpy surface), all in linear RGB.
:func:`moving_mondrian` is a video of one: the Mondrian translates across the frame under a
moving light, with the true layers, the true optical flow and occlusions of every frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["SyntheticImage", "SyntheticSequence", "mondrian", "moving_mondrian"]


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


@dataclass(frozen=True)
class SyntheticSequence:
    """A video with its ground truth, linear RGB, ``images == reflectance * shading``.

    Attributes:
        images: ``(T, 3, H, W)`` the frames.
        reflectance: ``(T, 3, H, W)`` piecewise constant, values in ``[0.1, 0.9]``; the same
            surface in every frame, translated.
        shading: ``(T, 1, H, W)`` smooth, in ``[shading_min, 1]``; changes with the light.
        flow: ``(T - 1, 2, H, W)`` true optical flow ``(u, v)`` from frame ``t`` to ``t + 1``
            (pixel ``(x, y)`` of frame ``t`` is at ``(x + u, y + v)`` in frame ``t + 1``).
        valid: ``(T - 1, 1, H, W)`` bool, pixels of frame ``t`` still visible in frame
            ``t + 1`` (not leaving the frame).
    """

    images: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor
    flow: torch.Tensor
    valid: torch.Tensor


def moving_mondrian(
    height: int = 72,
    width: int = 96,
    frames: int = 5,
    velocity: tuple[int, int] = (3, 1),
    patches: int = 14,
    light_step: float = 0.35,
    shading_min: float = 0.2,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> SyntheticSequence:
    """A Mondrian on a bumpy surface translating across the frame under a moving light.

    The surface (reflectance and relief) is drawn on a canvas larger than the frame; frame
    ``t`` shows the canvas window shifted by ``t · velocity``, so the content moves by
    ``−velocity`` px per frame. The shading is Lambertian, ``max(n · l_t, 0)`` rescaled to
    ``[shading_min, 1]``, of the relief's normals under a light whose azimuth turns by
    ``light_step`` radians per frame: shadows move over the surface while the reflectance
    stays put.

    Args:
        height: frame height.
        width: frame width.
        frames: number of frames ``T``.
        velocity: ``(vx, vy)`` integer window shift per frame in px (the content moves by
            minus that).
        patches: rectangles of the Mondrian.
        light_step: change of the light's azimuth per frame (radians).
        shading_min: darkest shading.
        seed: seed of a private generator.
        dtype: floating dtype of the outputs.

    Returns:
        :class:`SyntheticSequence`.

    >>> seq = moving_mondrian(40, 48, frames=3, velocity=(2, 1))
    >>> seq.images.shape, seq.flow.shape
    (torch.Size([3, 3, 40, 48]), torch.Size([2, 2, 40, 48]))
    >>> bool(torch.allclose(seq.reflectance[1, :, :-1, :-2], seq.reflectance[0, :, 1:, 2:]))
    True
    """
    vx, vy = (int(v) for v in velocity)
    ch = height + abs(vy) * (frames - 1)
    cw = width + abs(vx) * (frames - 1)
    canvas = mondrian(ch, cw, patches=patches, seed=seed, dtype=torch.float64).reflectance[0]
    g = torch.Generator().manual_seed(seed + 1)
    yy = torch.arange(ch, dtype=torch.float64).view(-1, 1)
    xx = torch.arange(cw, dtype=torch.float64).view(1, -1)
    relief = torch.zeros(ch, cw, dtype=torch.float64)
    scale = float(min(height, width))
    for _ in range(6):  # smooth bumps and dents
        cy, cx = float(torch.rand(1, generator=g)) * ch, float(torch.rand(1, generator=g)) * cw
        r = scale * (0.15 + 0.2 * float(torch.rand(1, generator=g)))
        amp = r * (0.6 if float(torch.rand(1, generator=g)) > 0.3 else -0.6)
        relief += amp * torch.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * r * r))
    gy, gx = torch.gradient(relief)
    normals = torch.stack([-gx, -gy, torch.ones_like(gx)])
    normals = normals / normals.norm(dim=0, keepdim=True)
    oy, ox = (abs(vy) * (frames - 1) if vy < 0 else 0), (abs(vx) * (frames - 1) if vx < 0 else 0)
    refl, shade = [], []
    azimuth0 = float(torch.rand(1, generator=g)) * 6.28
    elevation = 0.9  # radians from the vertical
    for t in range(frames):
        y0, x0 = oy + vy * t, ox + vx * t
        a = azimuth0 + light_step * t
        light = torch.tensor(
            [math.cos(a) * math.sin(elevation), math.sin(a) * math.sin(elevation)]
            + [math.cos(elevation)],
            dtype=torch.float64,
        )
        lam = (normals * light.view(3, 1, 1)).sum(0).clamp_min(0)
        s = shading_min + (1 - shading_min) * lam
        refl.append(canvas[:, y0 : y0 + height, x0 : x0 + width])
        shade.append(s[None, y0 : y0 + height, x0 : x0 + width])
    reflectance, shading = torch.stack(refl), torch.stack(shade)
    flow = torch.empty(max(frames - 1, 0), 2, height, width, dtype=torch.float64)
    flow[:, 0], flow[:, 1] = -vx, -vy
    ys = torch.arange(height).view(-1, 1) - vy
    xs = torch.arange(width).view(1, -1) - vx
    inside = (ys >= 0) & (ys < height) & (xs >= 0) & (xs < width)
    valid = inside.expand(max(frames - 1, 0), 1, height, width).clone()
    return SyntheticSequence(
        images=(reflectance * shading).to(dtype),
        reflectance=reflectance.to(dtype),
        shading=shading.to(dtype),
        flow=flow.to(dtype),
        valid=valid,
    )
