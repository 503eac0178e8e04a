"""Representative pixels ``Q`` of the global reflectance prior (paper §3.3, Eq. 10).

One pixel per segment: the pixel whose colour feature ``r̄`` is closest to the segment's mean
``r̄`` (ties: the smallest flat index). Segments come from a label map, e.g.
:func:`torchiid.features.segmentation.felzenszwalb_segments` (the paper uses MCG regions).
:func:`global_pair_term` then links every pair of representatives of an image,
``|Q|(|Q|−1)/2`` pairs weighted by ``v^g``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchiid.core.check import check_shape
from torchiid.core.exceptions import ShapeError
from torchiid.priors.reflectance_terms import PairL1Term, pair_affinity

__all__ = [
    "Representatives",
    "SegmentLayout",
    "segment_layout",
    "representative_pixels",
    "global_pair_term",
]


@dataclass(frozen=True)
class Representatives:
    """Representative pixels of each image, padded to the largest segment count ``Q``.

    Attributes:
        index: ``(B, Q)`` long, flat pixel index ``y·W + x`` (0 in padding).
        valid: ``(B, Q)`` bool, ``False`` in padding.
        label: ``(B, Q)`` long, the segment label each representative stands for (-1 in padding).
    """

    index: torch.Tensor
    valid: torch.Tensor
    label: torch.Tensor

    @property
    def counts(self) -> torch.Tensor:
        """``(B,)`` number of representatives per image."""
        return self.valid.sum(dim=1)


@dataclass(frozen=True)
class SegmentLayout:
    """Which pixels belong to which segment, for :func:`representative_pixels`.

    The part of the search that depends on the labels and the mask only, so the alternations
    on one image share it.

    Attributes:
        shape: ``(B, H, W)`` of the labels.
        bidx, pix: image and flat pixel index of every used pixel (label ``>= 0``, in the mask).
        seg: each used pixel's segment number in ``0 .. M-1`` (segments sorted by image, label).
        count: ``(M,)`` pixels per segment.
        seg_b, pos, seg_l: each segment's image, position among its image's segments, label.
        q: the largest segment count of an image.
        dense: every pixel of every image is used (the features need no gather).
    """

    shape: tuple[int, int, int]
    bidx: torch.Tensor
    pix: torch.Tensor
    seg: torch.Tensor
    count: torch.Tensor
    seg_b: torch.Tensor
    pos: torch.Tensor
    seg_l: torch.Tensor
    q: int
    dense: bool


def segment_layout(labels: torch.Tensor, mask: torch.Tensor | None = None) -> SegmentLayout:
    """The :class:`SegmentLayout` of a label map; see :func:`representative_pixels`.

    Shape:
        labels ``(B, H, W)`` integer, mask ``(B, 1, H, W)``.
    """
    check_shape(labels, ("B", "H", "W"), "labels")
    b, h, w = labels.shape
    if labels.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8):
        raise ShapeError(f"expected integer labels, got {labels.dtype}")
    n = h * w
    lab = labels.reshape(b, n).long()
    use = lab >= 0
    if mask is not None:
        check_shape(mask, (b, 1, h, w), "mask")
        use = use & mask.reshape(b, n).bool()
    bidx, pix = torch.nonzero(use, as_tuple=True)
    dev = labels.device
    if bidx.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return SegmentLayout((b, h, w), empty, empty, empty, empty, empty, empty, empty, 0, False)
    lab_u = lab[bidx, pix]
    span = int(lab_u.max()) + 1
    key = bidx * span + lab_u
    # the used keys, sorted (by image, then label), and each pixel's rank among them: a
    # counting pass instead of torch.unique's sort, unless labels are sparse (huge ids)
    if int(key.max()) < 4 * key.numel():
        present = torch.bincount(key) > 0
        seg_keys = torch.nonzero(present).squeeze(1)
        seg = (torch.cumsum(present, 0, dtype=torch.long) - 1)[key]
    else:
        seg_keys, seg = torch.unique(key, return_inverse=True)
    m = seg_keys.numel()
    count = torch.bincount(seg, minlength=m)
    seg_b = torch.div(seg_keys, span, rounding_mode="floor")
    seg_l = seg_keys - seg_b * span
    per_image = torch.bincount(seg_b, minlength=b)
    start = torch.cumsum(per_image, 0) - per_image
    pos = torch.arange(m, device=dev) - start[seg_b]
    dense = bidx.numel() == b * n
    return SegmentLayout(
        (b, h, w), bidx, pix, seg, count, seg_b, pos, seg_l, int(per_image.max()), dense
    )


def representative_pixels(
    features: torch.Tensor,
    labels: torch.Tensor,
    mask: torch.Tensor | None = None,
    layout: SegmentLayout | None = None,
) -> Representatives:
    """The pixel closest to its segment's mean feature, one per segment.

    Args:
        features: per-pixel features, e.g. ``r̄`` from
            :func:`~torchiid.priors.reflectance_terms.lab_features`.
        labels: segment label per pixel; labels ``< 0`` and pixels outside ``mask`` belong to
            no segment (the mean is taken over the remaining pixels of each segment).
        mask: optional bool mask of usable pixels.
        layout: :func:`segment_layout` of ``labels`` and ``mask``, computed once when the
            same segments are used with several feature maps (the same result).

    Shape:
        features ``(B, D, H, W)``, labels ``(B, H, W)`` long, mask ``(B, 1, H, W)``.

    >>> f = torch.tensor([0.0, 0.1, 0.9, 1.0]).view(1, 1, 1, 4)
    >>> representative_pixels(f, torch.tensor([[[0, 0, 0, 1]]])).index
    tensor([[1, 3]])
    """
    check_shape(features, ("B", "D", "H", "W"), "features")
    b, d, h, w = features.shape
    check_shape(labels, (b, h, w), "labels")
    if layout is None:
        layout = segment_layout(labels, mask)
    elif layout.shape != (b, h, w):
        raise ShapeError(f"layout is for labels of shape {layout.shape}, not {(b, h, w)}")
    n = h * w
    dev = features.device
    if layout.bidx.numel() == 0:
        empty = torch.zeros(b, 0, dtype=torch.long, device=dev)
        return Representatives(empty, empty.bool(), empty)
    seg, pix = layout.seg, layout.pix
    m = layout.count.numel()
    if layout.dense:  # every pixel used, in order: a transpose instead of a gather
        f = features.reshape(b, d, n).transpose(1, 2).reshape(b * n, d)
    else:
        f = features.reshape(b, d, n)[layout.bidx, :, pix]  # (n_used, D)
    count = layout.count.to(f.dtype)
    mean = f.new_zeros(m, d).index_add_(0, seg, f) / count.unsqueeze(1)
    dist = (f - mean[seg]).square().sum(dim=1)
    best = dist.new_full((m,), float("inf")).scatter_reduce_(0, seg, dist, "amin")
    is_best = dist <= best[seg]
    rep = torch.full((m,), n, dtype=torch.long, device=dev)
    rep.scatter_reduce_(0, seg[is_best], pix[is_best], "amin")
    q = layout.q
    index = torch.zeros(b, q, dtype=torch.long, device=dev)
    valid = torch.zeros(b, q, dtype=torch.bool, device=dev)
    label = torch.full((b, q), -1, dtype=torch.long, device=dev)
    index[layout.seg_b, layout.pos] = rep
    valid[layout.seg_b, layout.pos] = True
    label[layout.seg_b, layout.pos] = layout.seg_l
    return Representatives(index, valid, label)


def global_pair_term(features: torch.Tensor, reps: Representatives, t: float) -> PairL1Term:
    """All pairs of representatives per image, weights ``v^g`` (Eqs. 7, 10), as ``C``.

    Args:
        features: ``r̄`` of the current reflectance.
        reps: from :func:`representative_pixels`.
        t: weight deviation.

    Shape:
        features ``(B, D, H, W)`` -> a :class:`PairL1Term` with ``P = Q(Q−1)/2`` pairs per image
        (pairs involving padding get weight 0).
    """
    b, _, h, w = features.shape
    q = reps.index.shape[1]
    pi, pj = torch.triu_indices(q, q, offset=1, device=features.device)
    i = reps.index[:, pi]
    j = reps.index[:, pj]
    ok = (reps.valid[:, pi] & reps.valid[:, pj]).to(features.dtype)
    weights = pair_affinity(features, i, j, t) * ok
    return PairL1Term(i, j, weights, h, w)
