"""Selecting an object by clicking on it: the selective-search proposals under the click.

Stage 0 already computed the photo's object proposals (selective search, at the working
resolution) for the mid-level prior; :class:`Objects` keeps them as atoms (pixels that every
segmentation puts together) and which atoms each proposal holds. A click picks the proposals
that contain the pixel, from the smallest to the whole photo: nested regions (the coffee,
the cup, cup and saucer, ...) between which the page's "selection size" slider chooses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from torchiid.features import selective_search

__all__ = ["Objects", "highlight"]

#: proposals smaller than this share of the photo are not offered (texture specks)
MIN_FRACTION = 0.004
#: a candidate whose area is within this factor of the previous one is a near-duplicate
SAME_AREA = 1.03


@dataclass(frozen=True)
class Objects:
    """A photo's object proposals at the working resolution.

    Attributes:
        labels: ``(h, w)`` long, the atom of every pixel.
        member: ``(A, P)`` bool, ``member[a, p]``: atom ``a`` lies in proposal ``p``.
        areas: ``(P,)`` float64 pixel count of every proposal.
    """

    labels: torch.Tensor
    member: torch.Tensor
    areas: torch.Tensor

    @classmethod
    def from_features(cls, features: object) -> Objects | None:
        """The proposals Stage 0 computed (``Decomposition.features``), if it did."""
        midlevel = getattr(features, "midlevel", None)
        if midlevel is None:
            return None
        one = midlevel[0]
        member = (one.atom_g > 0).cpu()
        areas = one.atom_sizes.cpu().double() @ member.double()
        return cls(one.atom_labels.cpu(), member, areas)

    @classmethod
    def from_image(cls, image: torch.Tensor) -> Objects:
        """Selective search on a ``(1, 3, h, w)`` linear image (when Stage 0 had no proposals)."""
        props = selective_search(image[0].cpu())
        return cls(props.atom_labels, props.membership, props.areas.double())

    @property
    def size(self) -> tuple[int, int]:
        """``(h, w)``."""
        return int(self.labels.shape[0]), int(self.labels.shape[1])

    def under(self, u: float, v: float) -> list[int]:
        """The proposals containing the point at ``(u, v)``, smallest first.

        Args:
            u: horizontal position as a fraction of the width, in ``[0, 1]``.
            v: vertical position as a fraction of the height.

        Returns:
            proposal indices by increasing area; proposals under :data:`MIN_FRACTION` of the
            photo and near-duplicates (an area within :data:`SAME_AREA` of the previous one)
            are left out.
        """
        h, w = self.size
        x = min(max(int(u * w), 0), w - 1)
        y = min(max(int(v * h), 0), h - 1)
        atom = int(self.labels[y, x])
        found = self.member[atom].nonzero()[:, 0]
        areas = self.areas[found]
        order = torch.argsort(areas, stable=True)
        kept: list[int] = []
        last = 0.0
        for i in order.tolist():
            area = float(areas[i])
            if area < MIN_FRACTION * h * w or area <= last * SAME_AREA:
                continue
            kept.append(int(found[i]))
            last = area
        return kept

    def mask(self, proposal: int, size: tuple[int, int] | None = None) -> torch.Tensor:
        """``(1, 1, H, W)`` bool mask of one proposal, at ``size`` (default: its own).

        Another size is reached by bilinear interpolation of the mask, thresholded at 1/2.
        """
        m = self.member[:, proposal][self.labels]
        if size is None or tuple(size) == self.size:
            return m[None, None]
        up = F.interpolate(m[None, None].float(), size=tuple(size), mode="bilinear")
        return up > 0.5


def highlight(rgb: np.ndarray, mask: torch.Tensor) -> np.ndarray:
    """An ``(h, w, 3)`` uint8 image with everything outside ``mask`` darkened."""
    m = mask.reshape(mask.shape[-2:]).numpy()
    if m.shape != rgb.shape[:2]:
        m = F.interpolate(mask.reshape(1, 1, *m.shape).float(), size=rgb.shape[:2]) > 0.5
        m = m[0, 0].numpy()
    out = rgb.copy()
    out[~m] = (out[~m] // 3).astype(np.uint8)
    return out
