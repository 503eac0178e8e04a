"""Representative pixels ``Q`` of the global reflectance prior (paper §3.3, Eq. 10).

One pixel per segment: the pixel whose colour feature ``r̄`` is closest to the segment's mean
``r̄`` (ties: the smallest flat index). Segments come from a label map, e.g.
:func:`felzenszwalb_segments` (the paper uses MCG regions). :func:`global_pair_term` then links
every pair of representatives of an image, ``|Q|(|Q|−1)/2`` pairs weighted by ``v^g``.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass

import kornia
import numpy as np
import torch

from torchiid.core.check import check_image, check_shape
from torchiid.core.exceptions import ShapeError
from torchiid.priors.reflectance_terms import PairL1Term, pair_affinity

__all__ = [
    "Representatives",
    "representative_pixels",
    "felzenszwalb_segments",
    "start_felzenszwalb_segments",
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


def representative_pixels(
    features: torch.Tensor, labels: torch.Tensor, mask: torch.Tensor | None = None
) -> Representatives:
    """The pixel closest to its segment's mean feature, one per segment.

    Args:
        features: per-pixel features, e.g. ``r̄`` from
            :func:`~torchiid.priors.reflectance_terms.lab_features`.
        labels: segment label per pixel; labels ``< 0`` and pixels outside ``mask`` belong to
            no segment (the mean is taken over the remaining pixels of each segment).
        mask: optional bool mask of usable pixels.

    Shape:
        features ``(B, D, H, W)``, labels ``(B, H, W)`` long, mask ``(B, 1, H, W)``.

    >>> f = torch.tensor([0.0, 0.1, 0.9, 1.0]).view(1, 1, 1, 4)
    >>> representative_pixels(f, torch.tensor([[[0, 0, 0, 1]]])).index
    tensor([[1, 3]])
    """
    check_shape(features, ("B", "D", "H", "W"), "features")
    b, d, h, w = features.shape
    check_shape(labels, (b, h, w), "labels")
    if labels.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8):
        raise ShapeError(f"expected integer labels, got {labels.dtype}")
    n = h * w
    lab = labels.reshape(b, n).long()
    use = lab >= 0
    if mask is not None:
        check_shape(mask, (b, 1, h, w), "mask")
        use = use & mask.reshape(b, n).bool()
    bidx, pix = torch.nonzero(use, as_tuple=True)
    dev = features.device
    if bidx.numel() == 0:
        empty = torch.zeros(b, 0, dtype=torch.long, device=dev)
        return Representatives(empty, empty.bool(), empty)
    lab_u = lab[bidx, pix]
    key = bidx * (int(lab_u.max()) + 1) + lab_u
    # the used keys, sorted (by image, then label), and each pixel's rank among them: a
    # counting pass instead of torch.unique's sort, unless labels are sparse (huge ids)
    if int(key.max()) < 4 * key.numel():
        present = torch.bincount(key) > 0
        seg_keys = torch.nonzero(present).squeeze(1)
        seg = (torch.cumsum(present, 0) - 1)[key]
    else:
        seg_keys, seg = torch.unique(key, return_inverse=True)
    m = seg_keys.numel()
    f = features.reshape(b, d, n)[bidx, :, pix]  # (n_used, D)
    count = torch.bincount(seg, minlength=m).to(f.dtype)
    mean = f.new_zeros(m, d).index_add_(0, seg, f) / count.unsqueeze(1)
    dist = (f - mean[seg]).square().sum(dim=1)
    best = dist.new_full((m,), float("inf")).scatter_reduce_(0, seg, dist, "amin")
    is_best = dist <= best[seg]
    rep = torch.full((m,), n, dtype=torch.long, device=dev)
    rep.scatter_reduce_(0, seg[is_best], pix[is_best], "amin")
    seg_b = torch.div(seg_keys, int(lab_u.max()) + 1, rounding_mode="floor")
    seg_l = seg_keys - seg_b * (int(lab_u.max()) + 1)
    per_image = torch.bincount(seg_b, minlength=b)
    start = torch.cumsum(per_image, 0) - per_image
    pos = torch.arange(m, device=dev) - start[seg_b]
    q = int(per_image.max())
    index = torch.zeros(b, q, dtype=torch.long, device=dev)
    valid = torch.zeros(b, q, dtype=torch.bool, device=dev)
    label = torch.full((b, q), -1, dtype=torch.long, device=dev)
    index[seg_b, pos] = rep
    valid[seg_b, pos] = True
    label[seg_b, pos] = seg_l
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


def felzenszwalb_segments(
    image: torch.Tensor,
    *,
    linear: bool = True,
    scale: float = 200.0,
    sigma: float = 0.8,
    min_size: int = 100,
) -> torch.Tensor:
    """Felzenszwalb–Huttenlocher superpixels per image (``graph_segmentation``).

    Runs on the sRGB encoding of the image in ``[0, 1]`` (``linear=True`` converts a linear input
    with ``kornia.color.linear_rgb_to_rgb`` after clamping). Defaults give about 150–300 segments
    on a 512×384 photo, so ``C`` has a few ten thousand pairs.

    Args:
        image: RGB image in ``[0, 1]``, linear (default) or sRGB.
        linear: whether ``image`` is linear RGB.
        scale: larger values give larger segments.
        sigma: Gaussian pre-smoothing width in pixels.
        min_size: smallest segment in pixels (smaller ones are merged).

    Shape:
        ``(B, 3, H, W) -> (B, H, W)`` long labels from 0, on the image's device.
    """
    return start_felzenszwalb_segments(
        image, linear=linear, scale=scale, sigma=sigma, min_size=min_size
    )()


def start_felzenszwalb_segments(
    image: torch.Tensor,
    *,
    linear: bool = True,
    scale: float = 200.0,
    sigma: float = 0.8,
    min_size: int = 100,
    executor: Executor | None = None,
) -> Callable[[], torch.Tensor]:
    """:func:`felzenszwalb_segments` that can run in the background.

    The torch part (sRGB encoding) runs now, in the calling thread; the segmentation itself
    (OpenCV's C++, which releases the GIL) is submitted to ``executor`` when given, so it
    overlaps whatever the caller does next. Call the returned function for the labels.
    """
    from torchiid.features.segmentation import graph_segmentation

    check_image(image, "image")
    srgb = image.clamp(0.0, 1.0)
    if linear:
        srgb = kornia.color.linear_rgb_to_rgb(srgb)
    arr = srgb.detach().to("cpu", torch.float32).permute(0, 2, 3, 1).numpy()
    device = image.device

    def run() -> list[np.ndarray]:
        return [graph_segmentation(a, scale=scale, sigma=sigma, min_size=min_size) for a in arr]

    future = executor.submit(run) if executor is not None else None

    def result() -> torch.Tensor:
        out = future.result() if future is not None else run()
        return torch.from_numpy(np.stack(out).astype(np.int64)).to(device)

    return result
