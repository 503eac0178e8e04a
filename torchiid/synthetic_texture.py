"""Textured planes under smooth light, with known reflectance and shading.

A test set for texture that belongs to the reflectance: :func:`textured_plane` draws one of
five flat, textured surfaces (:data:`TEXTURES`) and lights it with one of two smooth lights
(:data:`LIGHTS`); :func:`texture_set` gives all ten. All layers are linear RGB and
``image == reflectance * shading`` exactly.

Textures (each varies mostly in lightness within one hue, which is what the chromaticity-based
Retinex term cannot tell from shading):

- ``tiles``: off-white square tiles of slightly varying lightness with gray grout lines;
- ``wood``: brown boards with growth rings and fine streaks, darker grain a little redder;
- ``print``: a label: black text on a cream ground and cream text on a red band;
- ``fabric``: a twill-woven plaid of three colours with thin light over-check lines;
- ``fur``: tan strands (noise drawn out along a slanted direction) with a few darker stripes.

Lights: ``gradient``, a point light above the plane (inverse-square fall-off and the cosine,
plus ambient light), and ``shadow``, the same with a soft-edged cast shadow (an occluder's
polygon, blurred) where the light drops to 35%.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from torchiid.core.exceptions import ParameterError

__all__ = ["LIGHTS", "TEXTURES", "TexturedPlane", "smooth_light", "texture_set", "textured_plane"]

TEXTURES = ("tiles", "wood", "print", "fabric", "fur")
"""The texture kinds of :func:`textured_plane`."""

LIGHTS = ("gradient", "shadow")
"""The lights of :func:`textured_plane`."""


@dataclass(frozen=True)
class TexturedPlane:
    """A textured plane under smooth light, ``image == reflectance * shading``.

    Attributes:
        image: ``(1, 3, H, W)`` linear RGB.
        reflectance: ``(1, 3, H, W)`` the texture, values in ``[0.02, 0.95]``.
        shading: ``(1, 1, H, W)`` the light, smooth, maximum 1.
        texture: the texture kind.
        light: the light kind.
    """

    image: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor
    texture: str
    light: str


def _noise(rng: np.random.Generator, h: int, w: int, sx: float, sy: float) -> np.ndarray:
    """White noise blurred by a Gaussian of scales ``(sx, sy)``, normalised to std 1."""
    n = cv2.GaussianBlur(
        rng.standard_normal((h, w)), (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REFLECT
    )
    return (n - n.mean()) / max(float(n.std()), 1e-12)


def _tiles(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    side = max(12, min(h, w) // 8)
    grout = max(2, side // 10)
    yy, xx = np.mgrid[0:h, 0:w]
    row, col = yy // side, xx // side
    level = rng.uniform(0.9, 1.08, size=(row.max() + 1, col.max() + 1))[row, col]
    speckle = 1 + 0.04 * _noise(rng, h, w, 1.0, 1.0)
    tile = np.array([0.82, 0.80, 0.76]) * (level * speckle)[..., None]
    is_grout = ((yy % side) < grout) | ((xx % side) < grout)
    return np.where(is_grout[..., None], np.array([0.32, 0.31, 0.30]), tile)


def _wood(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    yy = np.mgrid[0:h, 0:w][0].astype(np.float64)
    period = max(6.0, h / 28)
    phase = yy + 0.6 * period * _noise(rng, h, w, w / 10, h / 20)
    rings = np.sin(2 * np.pi * phase / period)
    streaks = _noise(rng, h, w, max(4.0, w / 30), 0.7)
    f = np.clip(0.8 + 0.15 * rings + 0.07 * streaks, 0.4, 1.2)
    # darker grain is a little more saturated (redder), as in real wood
    return np.array([0.50, 0.31, 0.16]) * f[..., None] ** np.array([1.0, 1.1, 1.25])


def _print(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    cream, red, ink = np.array([0.86, 0.82, 0.66]), np.array([0.62, 0.10, 0.08]), 0.04
    band = np.zeros((h, w), np.float32)
    band[int(0.08 * h) : int(0.30 * h), :] = 1
    black, light = np.zeros((h, w), np.uint8), np.zeros((h, w), np.uint8)
    scale = min(h, w) / 256
    words = [
        "INTRINSIC",
        "Reflectance x Shading",
        "net wt 250 g  lot 0421",
        "best before 2027",
        "ingredients: water, salt",
        "keep in a cool dry place",
        "made in torchiid",
    ]
    y = int(0.26 * h)
    x0 = int(0.06 * w + rng.integers(0, max(1, w // 40)))
    cv2.putText(
        light,
        words[0],
        (x0, y),
        cv2.FONT_HERSHEY_DUPLEX,
        1.1 * scale,
        255,
        max(1, round(2 * scale)),
        cv2.LINE_AA,
    )
    for i, text in enumerate(words[1:]):
        y = int(0.42 * h + i * 0.11 * h)
        cv2.putText(
            black,
            text,
            (x0, y),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.55 * scale,
            255,
            max(1, round(scale)),
            cv2.LINE_AA,
        )
    black, light = black[..., None] / 255.0, light[..., None] / 255.0  # anti-aliased coverage
    ground = band[..., None] * red + (1 - band[..., None]) * cream
    out = ground * (1 - light) + cream * light
    return out * (1 - black) + ink * black


def _fabric(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    colours = np.array([[0.07, 0.09, 0.28], [0.55, 0.08, 0.08], [0.78, 0.72, 0.56]])
    period = max(12, min(h, w) // 10)
    pattern = np.array([0, 0, 1, 2, 2, 1])  # stripe colours along a period
    yy, xx = np.mgrid[0:h, 0:w]
    shift = int(rng.integers(0, period))
    warp = colours[pattern[((xx + shift) * len(pattern) // period) % len(pattern)]]
    weft = colours[pattern[((yy + shift) * len(pattern) // period) % len(pattern)]]
    twill = (((xx + yy) // 2) % 2 == 0)[..., None]
    out = np.where(twill, warp, weft)
    over = ((xx % (2 * period)) == period // 2) | ((yy % (2 * period)) == period // 2)
    return np.where(over[..., None], np.array([0.90, 0.88, 0.80]), out)


def _fur(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    big = int(1.5 * max(h, w)) + 2
    n = _noise(rng, big, big, max(5.0, w / 40), 0.6)
    rot = cv2.getRotationMatrix2D((big / 2, big / 2), 30, 1.0)
    n = cv2.warpAffine(n, rot, (big, big), flags=cv2.INTER_LINEAR)
    y0, x0 = (big - h) // 2, (big - w) // 2
    n = n[y0 : y0 + h, x0 : x0 + w]
    n = (n - n.mean()) / max(float(n.std()), 1e-12)
    yy, xx = np.mgrid[0:h, 0:w]
    stripes = np.sin(2 * np.pi * (xx + 0.5 * yy) / max(24.0, w / 5) + 2 * _noise(rng, h, w, 12, 12))
    f = np.exp(0.22 * n - 0.25 * np.clip(stripes, 0, None))
    return np.array([0.62, 0.45, 0.28]) * f[..., None] ** np.array([1.0, 1.08, 1.2])


_MAKERS = {"tiles": _tiles, "wood": _wood, "print": _print, "fabric": _fabric, "fur": _fur}


def smooth_light(light: str, height: int, width: int, seed: int = 0) -> torch.Tensor:
    """The shading of :func:`textured_plane`: ``(1, 1, H, W)`` float64, maximum 1."""
    if light not in LIGHTS:
        raise ParameterError(f"unknown light {light!r}; choose one of {', '.join(LIGHTS)}")
    rng = np.random.default_rng(seed + 1000)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    lx, ly = -0.3 * width + rng.uniform(-0.05, 0.05) * width, 0.2 * height
    z = 0.9 * max(height, width)
    s = (z / np.sqrt((xx - lx) ** 2 + (yy - ly) ** 2 + z**2)) ** 3
    s = 0.1 + 0.9 * s / s.max()
    if light == "shadow":
        occluder = np.zeros((height, width), np.float64)
        pts = np.array([[0.45, 0.0], [0.75, 0.0], [0.95, 1.0], [0.55, 1.0]])
        pts = (pts * [width, height]).astype(np.int32)
        cv2.fillPoly(occluder, [pts], 1.0)
        soft = max(3.0, min(height, width) / 32)
        occluder = cv2.GaussianBlur(occluder, (0, 0), soft, borderType=cv2.BORDER_REPLICATE)
        s = s * (1 - 0.65 * occluder)
    return torch.from_numpy(s / s.max())[None, None]


def textured_plane(
    texture: str,
    light: str,
    height: int = 256,
    width: int = 256,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> TexturedPlane:
    """One textured plane under one smooth light (see the module docstring).

    Args:
        texture: one of :data:`TEXTURES`.
        light: one of :data:`LIGHTS`.
        height: image height (at least 32).
        width: image width (at least 32).
        seed: seed of the texture's and the light's random choices.
        dtype: floating dtype of the layers.

    Example:
        >>> s = textured_plane("wood", "shadow", 64, 80)
        >>> s.image.shape, bool(torch.allclose(s.image, s.reflectance * s.shading))
        (torch.Size([1, 3, 64, 80]), True)
    """
    if texture not in _MAKERS:
        raise ParameterError(f"unknown texture {texture!r}; choose one of {', '.join(TEXTURES)}")
    if min(height, width) < 32:
        raise ParameterError(f"textured planes need sides of at least 32 px, got {height}x{width}")
    shading = smooth_light(light, height, width, seed)
    rng = np.random.default_rng(seed)
    refl = np.clip(_MAKERS[texture](rng, height, width), 0.02, 0.95)
    refl_t = torch.from_numpy(np.ascontiguousarray(refl.transpose(2, 0, 1)))[None]
    refl_t, shading = refl_t.to(dtype), shading.to(dtype)
    return TexturedPlane(refl_t * shading, refl_t, shading, texture, light)


def texture_set(height: int = 256, width: int = 256, seed: int = 0) -> dict[str, TexturedPlane]:
    """Every texture under every light, keyed ``"<texture>-<light>"`` (10 images)."""
    return {
        f"{t}-{lt}": textured_plane(t, lt, height, width, seed) for t in TEXTURES for lt in LIGHTS
    }
