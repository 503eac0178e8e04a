"""Checks, masks, safe division, the white level and the Gaussian filter of the edits."""

from __future__ import annotations

import math

import kornia
import torch
import torch.nn.functional as F

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.core.stats import image_quantile

__all__ = ["default_blur", "gaussian"]

#: the smallest denominator, shading level and light peak the edits divide by
EPS = 1e-6


def default_blur(height: int, width: int) -> float:
    """The default Gaussian σ in pixels of the residue filters: 1% of the longer side, >= 1."""
    return max(1.0, 0.01 * max(height, width))


#: the largest σ in pixels that :func:`gaussian` applies at the image's own resolution
FAST_SIGMA = 4.0


def gaussian(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``(B, C, H, W)`` with σ in pixels (replicated borders).

    A σ of at least twice :data:`FAST_SIGMA` is applied to a copy area-averaged by the
    integer factor ``f = σ // FAST_SIGMA`` and brought back by bilinear interpolation, both
    of which blur too (variances ``(f² − 1) / 12`` and about ``f² / 6`` px²), so the Gaussian
    there has the rest; the borders are replicated at the image's own resolution first. A
    blur whose kernel spans hundreds of pixels (the edits' residue filters on a 12-megapixel
    photo) then costs about ``f²`` times fewer pixels and ``f`` times fewer taps, and differs
    from the exact blur by at most 0.3% of the signal's range.
    """
    if sigma <= 0:
        return x
    f = int(sigma // FAST_SIGMA)
    if f < 2:
        k = 2 * math.ceil(3 * sigma) + 1
        return kornia.filters.gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="replicate")
    h, w = x.shape[-2:]
    rest = math.sqrt(sigma * sigma - (f * f - 1) / 12 - f * f / 6) / f
    # replicated borders at the image's own resolution, as the exact blur has them: a margin
    # of the small kernel's reach, and a whole number of small pixels in all
    pad = f * (math.ceil(3 * rest) + 1)
    bottom, right = pad + (-(h + 2 * pad)) % f, pad + (-(w + 2 * pad)) % f
    big = F.pad(x, (pad, right, pad, bottom), mode="replicate")
    small = F.avg_pool2d(big, f)
    up = F.interpolate(gaussian(small, rest), scale_factor=f, mode="bilinear", align_corners=False)
    return up[..., pad : pad + h, pad : pad + w]


def safe_div(a: torch.Tensor, b: torch.Tensor, default: float = 1.0) -> torch.Tensor:
    """``a / b`` where ``|b| > EPS``, else ``default``."""
    ok = b.abs() > EPS
    return torch.where(ok, a / torch.where(ok, b, torch.ones_like(b)), torch.full_like(a, default))


#: the largest factor an edit takes (a chroma factor, a light strength): far beyond it every
#: colour or light saturates, and float32 overflows into NaN
FACTOR_LIMIT = 1000.0


def check_number(
    value: float, name: str, *, low: float | None = None, high: float | None = None
) -> float:
    """``value`` as a float if it is a finite number in ``[low, high]``, else a ParameterError."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ParameterError(f"{name} must be a finite number, got {value!r}")
    if low is not None and x < low:
        raise ParameterError(f"{name} must be >= {low:g}, got {value!r}")
    if high is not None and x > high:
        raise ParameterError(f"{name} must be <= {high:g}, got {value!r}")
    return x


#: the lowest ``amount`` of :func:`~torchiid.edit.shadows.soften_shadows`: the log-shading's
#: contrast grows by ``1 − amount`` around the pivot, and at 11x a highlight a thousand times
#: the pivot already reaches e^76 (float32 ends at e^88)
MOST_HARDENING = -10.0

#: the largest tile of :func:`~torchiid.edit.retexture.replace_albedo`, as a multiple of the
#: photo's longer side: a larger one shows only its corner, and would be made whole first
MAX_TILE = 4


def check_edit_numbers(
    like: torch.Tensor,
    *,
    blur: float | None = None,
    feather: float | None = None,
    strength: float | None = None,
    intensity: bool = False,
    hue: float | None = None,
    chroma: float | None = None,
    amount: float | None = None,
    percentile: float | None = None,
    radius: float | None = None,
    scale: float | None = None,
    texture: torch.Tensor | None = None,
) -> None:
    """Refuse an edit's number that is not finite or outside its range, naming it.

    Every edit checks its own numbers here, and ``torchiid edit`` all of its options before
    it decomposes the photo. ``None`` skips a number. Bounds: ``blur`` and ``feather`` (σ in
    pixels) from 0 to ``like``'s longer side (a larger σ blurs to the mean as that does, and
    its padding grows with σ²); ``strength`` and ``chroma`` at most :data:`FACTOR_LIMIT`
    (``strength`` at least 0 for the light intensity (``intensity``), at least
    −:data:`FACTOR_LIMIT` for the light colour; ``chroma`` at least 0); ``amount`` in
    ``[MOST_HARDENING, 1]``; ``percentile`` in (0, 1); ``radius`` and ``scale`` above 0, and
    with a ``texture`` to tile, its tiles at most :data:`MAX_TILE` × ``like``'s longer side.
    Each message starts with the number's name.

    Raises:
        ParameterError: the first number out of its range.
    """
    side = float(max(like.shape[-2:]))
    for name, sigma in (("blur", blur), ("feather", feather)):
        if sigma is not None:
            check_number(sigma, name, low=0.0, high=side)
    if strength is not None:
        low = 0.0 if intensity else -FACTOR_LIMIT  # below 0 the intensity makes S negative
        check_number(strength, "strength", low=low, high=FACTOR_LIMIT)
    if hue is not None:
        check_number(hue, "hue")
    if chroma is not None:
        check_number(chroma, "chroma", low=0.0, high=FACTOR_LIMIT)
    if amount is not None:
        check_number(amount, "amount", low=MOST_HARDENING, high=1.0)
    if percentile is not None and not 0 < check_number(percentile, "percentile") < 1:
        raise ParameterError(f"percentile must be in (0, 1), got {percentile}")
    for name, value in (("radius", radius), ("scale", scale)):
        if value is not None and not check_number(value, name) > 0:
            raise ParameterError(f"{name} must be > 0, got {value}")
    if scale is not None and texture is not None:
        most = MAX_TILE * side / max(texture.shape[-2:])
        if scale > most:
            raise ParameterError(
                f"scale must be at most {most:.3g} for this texture and photo (tiles up to "
                f"{MAX_TILE}x the photo's longer side), got {scale:g}"
            )


def check_layers(image: torch.Tensor, *others: torch.Tensor | None) -> None:
    """Raise :class:`ShapeError` unless ``image`` is 4-D and every other layer matches its size."""
    if image.dim() != 4:
        raise ShapeError(f"expected a (B, C, H, W) tensor, got shape {tuple(image.shape)}")
    for o in others:
        if o is not None and (o.dim() != 4 or o.shape[-2:] != image.shape[-2:]):
            raise ShapeError(
                f"layer of shape {tuple(o.shape)} does not match the image {tuple(image.shape)}"
            )


def region(mask: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` bool mask (all-true when ``None``)."""
    if mask is None:
        return torch.ones_like(like[:, :1], dtype=torch.bool)
    if mask.dim() == 3:
        mask = mask[:, None] if mask.shape[0] == like.shape[0] and like.shape[0] > 1 else mask[None]
    check_layers(like, mask)
    return mask.to(like.device).bool().expand(like.shape[0], 1, -1, -1)


def white_level(shading: torch.Tensor, q: float = 0.99) -> torch.Tensor:
    """``(B, 1, 1, 1)`` ``q`` quantile of each image's shading luminance (>= EPS)."""
    y = shading.mean(1, keepdim=True)
    return image_quantile(y, q).clamp_min(EPS).view(-1, 1, 1, 1).to(shading)
