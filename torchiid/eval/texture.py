"""How much of an image's fine texture a shading estimate carries.

Fine texture and print on a surface (tiles' grout, wood grain, text, a fabric's pattern, fur)
belong to the reflectance; the light over a surface varies smoothly except at shadow edges and
creases. :func:`texture_in_shading` measures the share of the image's fine-scale variation that
an estimated shading copies, in log space:

``T = sqrt( E[hp(log S − log S₀)] / E[hp(log I − log S₀)] )``

- ``I`` is the image's luminance (channel mean; the shading is gray), ``S`` the estimate (gray)
  and ``S₀`` the true shading, or ``S₀ = 1`` when it is not known and the light can be assumed
  smooth at the measure's scale inside ``region``.
- ``hp`` is the residual of a local linear fit: at each pixel, a plane fitted by least squares
  to the values inside ``region`` with Gaussian weights of scale ``sigma`` px is subtracted.
  Constants and linear ramps (the global scale of ``S``, a smooth gradient of light) leave no
  residual, also at the region's rim; variation at scales well below ``sigma`` passes whole.
- ``E`` is the mean of the square over the pixels of ``region``.

So ``T`` is a ratio of root-mean-square amplitudes: 0 for a shading without the texture
(``S = S₀``, or any smooth light), 1 for a shading that copies all of it (``S = I``), and ``a``
for ``S = S₀ · (I / S₀)^a``. Shading errors at scales much larger than ``sigma`` (a wrong
overall gradient) do not count; a hard shadow edge left in ``log S − log S₀`` would. Without
the true shading, the measure on a photo is the share of the log-luminance's fine-scale
variation inside ``region`` that the shading carries, which is the texture in the shading only
as far as the true light there has no fine-scale variation of its own (no relief: brick mortar
grooves or gravel are partly shading).
"""

from __future__ import annotations

import torch

from torchiid.core.check import as_mask, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.core.local_fit import local_linear_residual

__all__ = ["local_linear_residual", "texture_in_shading"]


def _log_gray(x: torch.Tensor, m: torch.Tensor, eps: float, name: str) -> torch.Tensor:
    """``log`` of the channel mean, floored at ``eps`` times the maximum inside the region."""
    g = x.double().mean(1, keepdim=True)
    if bool((g < 0).any()) or not bool(torch.isfinite(g).all()):
        raise ParameterError(f"{name} must be finite and >= 0")
    top = torch.where(m, g, torch.zeros_like(g)).flatten(1).amax(1).view(-1, 1, 1, 1)
    return torch.log(torch.maximum(g, eps * top.clamp_min(1e-30)))


def texture_in_shading(
    shading: torch.Tensor,
    image: torch.Tensor,
    true_shading: torch.Tensor | None = None,
    region: torch.Tensor | None = None,
    sigma: float = 3.0,
    eps: float = 1e-4,
) -> torch.Tensor:
    """Share of the image's fine texture that ``shading`` carries (0: none, 1: all).

    See the module docstring for the definition. All inputs are linear and may have any
    global scale.

    Args:
        shading: ``(B, 1, H, W)`` or ``(B, 3, H, W)`` estimated shading (channel mean used).
        image: ``(B, C, H, W)`` the linear image it was estimated from.
        true_shading: ``(B, 1 or 3, H, W)`` the true shading, or ``None`` to assume the light
            is smooth at scale ``sigma`` inside ``region``.
        region: where to measure (e.g. an object mask, or a patch of even light); ``None``:
            the whole image.
        sigma: scale of the local linear fit, in pixels: variation at scales below it is
            texture.
        eps: logs of values below ``eps`` times the layer's maximum in the region are taken
            at that floor.

    Returns:
        ``(B,)`` float64; ``nan`` where the image has no fine-scale variation in the region.

    Example:
        >>> from torchiid.synthetic_texture import textured_plane
        >>> s = textured_plane("tiles", "gradient", 96, 96)
        >>> texture_in_shading(s.shading, s.image, s.shading).item() < 1e-6
        True
        >>> abs(texture_in_shading(s.image, s.image, s.shading).item() - 1) < 1e-6
        True
    """
    for name, t in (("shading", shading), ("image", image)):
        check_shape(t, ("B", "C", "H", "W"), name)
    if shading.shape[0] != image.shape[0] or shading.shape[-2:] != image.shape[-2:]:
        raise ShapeError(
            f"shading has shape {tuple(shading.shape)} but image has {tuple(image.shape)}"
        )
    m = as_mask(region, image, "region")
    if not bool(m.flatten(1).any(1).all()):
        raise ParameterError("the region holds no pixel in at least one image")
    log_s = _log_gray(shading, m, eps, "shading")
    log_i = _log_gray(image, m, eps, "image")
    if true_shading is not None:
        check_shape(true_shading, ("B", "C", "H", "W"), "true_shading")
        if true_shading.shape[0] != image.shape[0] or true_shading.shape[-2:] != image.shape[-2:]:
            raise ShapeError(
                f"true_shading has shape {tuple(true_shading.shape)} but image has "
                f"{tuple(image.shape)}"
            )
        log_t = _log_gray(true_shading, m, eps, "true_shading")
        log_s, log_i = log_s - log_t, log_i - log_t
    n = m.flatten(1).sum(1)
    num = local_linear_residual(log_s, m, sigma).square().flatten(1).sum(1) / n
    den = local_linear_residual(log_i, m, sigma).square().flatten(1).sum(1) / n
    # below ~1e-18 (a residual of 1e-9 in log) the image is flat up to round-off
    return torch.where(den > 1e-18, (num / den.clamp_min(1e-300)).sqrt(), float("nan"))
