"""Trivial reference decompositions: all of the image in one layer, a constant in the other.

They give the reference rows of an evaluation: a method should beat both.

- :func:`reflectance_is_image` (``R = I``): reflectance = image, shading = 1.
- :func:`shading_is_image` (``S = I``): shading = gray image (channel mean),
  reflectance = 1.

Both satisfy ``reflectance * shading == image`` only for gray images; they are scoring
references, not decompositions. Their layers are the same inside and outside any mask, so the
``mask`` argument is unused; it is there so that every method has the signature
``method(image, mask)``.
"""

from __future__ import annotations

import torch

from torchiid.baselines.result import BaselineResult
from torchiid.core.check import check_shape

__all__ = ["reflectance_is_image", "shading_is_image"]


def reflectance_is_image(image: torch.Tensor, mask: torch.Tensor | None = None) -> BaselineResult:
    """The ``R = I`` baseline: reflectance = image, shading = 1.

    Args:
        image: linear RGB ``(B, 3, H, W)``.
        mask: unused (see the module notes).

    Returns:
        ``reflectance`` a copy of ``image`` ``(B, 3, H, W)`` and ``shading`` ones
        ``(B, 1, H, W)``, dtype and device of ``image``.

    Example:
        >>> out = reflectance_is_image(torch.rand(2, 3, 8, 8))
        >>> out.reflectance.shape, out.shading.shape
        (torch.Size([2, 3, 8, 8]), torch.Size([2, 1, 8, 8]))
    """
    check_shape(image, ("B", 3, "H", "W"), "image")
    return BaselineResult(image.clone(), image.new_ones(image.shape[0], 1, *image.shape[-2:]))


def shading_is_image(image: torch.Tensor, mask: torch.Tensor | None = None) -> BaselineResult:
    """The ``S = I`` baseline: shading = gray image (channel mean), reflectance = 1.

    Args:
        image: linear RGB ``(B, 3, H, W)``.
        mask: unused (see the module notes).

    Returns:
        ``reflectance`` ones ``(B, 3, H, W)`` and ``shading`` the channel mean of ``image``
        ``(B, 1, H, W)``, dtype and device of ``image``.

    Example:
        >>> out = shading_is_image(torch.rand(2, 3, 8, 8))
        >>> out.reflectance.shape, out.shading.shape
        (torch.Size([2, 3, 8, 8]), torch.Size([2, 1, 8, 8]))
    """
    check_shape(image, ("B", 3, "H", "W"), "image")
    return BaselineResult(torch.ones_like(image), image.mean(dim=1, keepdim=True))
