"""Bilinear RoI-align (He et al. 2017, "Mask R-CNN") on top of ``grid_sample``.

torchvision is not a dependency; this is the ``aligned=True`` variant of
``torchvision.ops.roi_align`` with a fixed positive ``sampling_ratio``. Coordinates are continuous:
feature cell ``j`` spans ``[j, j + 1)`` after multiplying by ``spatial_scale``, so a sample point
``u`` is read at cell index ``u - 0.5``. Unlike torchvision, samples outside the map are clamped
to the border (torchvision zeroes samples more than one cell outside), which only matters for
boxes that leave the feature map.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from torchiid.core.check import check_shape
from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = ["RoIAlign", "roi_align"]


def roi_align(
    features: torch.Tensor,
    boxes: torch.Tensor,
    output_size: int | tuple[int, int],
    spatial_scale: float = 1.0,
    sampling_ratio: int = 2,
) -> torch.Tensor:
    """Pool a ``(ph, pw)`` grid of bins from each box by averaging bilinear samples.

    Each bin averages ``sampling_ratio x sampling_ratio`` bilinear samples placed at the centres
    of a regular sub-grid of the bin.

    Args:
        features: feature maps ``(B, C, h, w)``, floating dtype.
        boxes: ``(x1, y1, x2, y2)`` per box, either ``(N, 4)`` (the same boxes for every image)
            or ``(B, N, 4)``; in input coordinates that ``spatial_scale`` maps to the map.
        output_size: bins per box, ``ph`` (= ``pw`` if an int) or ``(ph, pw)``.
        spatial_scale: factor from box coordinates to feature-map coordinates.
        sampling_ratio: samples per bin along each axis (``>= 1``).

    Returns:
        Pooled features ``(B, N, C, ph, pw)``, dtype and device of ``features``.

    Shape:
        - features: ``(B, C, h, w)``
        - boxes: ``(N, 4)`` or ``(B, N, 4)``
        - output: ``(B, N, C, ph, pw)``

    Raises:
        ShapeError: wrong tensor ranks or a batch mismatch.
        ParameterError: non-positive ``output_size`` or ``sampling_ratio``.
    """
    check_shape(features, ("B", "C", "h", "w"), "features")
    ph, pw = (output_size, output_size) if isinstance(output_size, int) else output_size
    if ph < 1 or pw < 1 or sampling_ratio < 1:
        raise ParameterError(
            f"output_size and sampling_ratio must be >= 1, got {output_size} and {sampling_ratio}"
        )
    b, _, h, w = features.shape
    if boxes.dim() == 2:
        check_shape(boxes, ("N", 4), "boxes")
        boxes = boxes.expand(b, -1, -1)
    else:
        check_shape(boxes, ("B", "N", 4), "boxes")
        if boxes.shape[0] != b:
            raise ShapeError(f"boxes hold {boxes.shape[0]} images but features hold {b}")
    n = boxes.shape[1]
    boxes = boxes.to(device=features.device, dtype=features.dtype) * spatial_scale
    x1, y1, x2, y2 = boxes.unbind(-1)  # (B, N) each
    s = sampling_ratio
    opts = {"device": features.device, "dtype": features.dtype}
    fy = (torch.arange(ph * s, **opts) + 0.5) / (ph * s)
    fx = (torch.arange(pw * s, **opts) + 0.5) / (pw * s)
    ys = y1[..., None] + fy * (y2 - y1)[..., None]  # (B, N, ph*s), continuous coordinates
    xs = x1[..., None] + fx * (x2 - x1)[..., None]
    # grid_sample (align_corners=False) reads cell index u - 0.5 at normalised 2u / size - 1.
    gy = (2.0 * ys / h - 1.0)[..., :, None].expand(b, n, ph * s, pw * s)
    gx = (2.0 * xs / w - 1.0)[..., None, :].expand(b, n, ph * s, pw * s)
    grid = torch.stack((gx, gy), dim=-1).reshape(b, n * ph * s, pw * s, 2)
    samples = F.grid_sample(
        features, grid, mode="bilinear", padding_mode="border", align_corners=False
    )  # (B, C, N*ph*s, pw*s)
    c = features.shape[1]
    pooled = samples.reshape(b, c, n, ph, s, pw, s).mean(dim=(4, 6))
    return pooled.permute(0, 2, 1, 3, 4)


class RoIAlign(nn.Module):
    """Module twin of :func:`roi_align`.

    Shape:
        ``(B, C, h, w)``, boxes ``(N, 4)`` or ``(B, N, 4)`` -> ``(B, N, C, ph, pw)``.
    """

    def __init__(
        self,
        output_size: int | tuple[int, int],
        spatial_scale: float = 1.0,
        sampling_ratio: int = 2,
    ) -> None:
        super().__init__()
        self.output_size = output_size
        self.spatial_scale = spatial_scale
        self.sampling_ratio = sampling_ratio

    def forward(self, features: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """Pool the boxes from the features; see :func:`roi_align`."""
        return roi_align(features, boxes, self.output_size, self.spatial_scale, self.sampling_ratio)
