"""Selective-search object proposals as region masks (paper §3.1.2).

The paper takes region masks and objectness scores from MCG. torchiid uses selective search
(Uijlings et al. 2013, "Selective Search for Object Recognition", IJCV): for every *strategy*
(a colour space, a Felzenszwalb scale ``k`` and a similarity combination), the image is
over-segmented with Felzenszwalb's method
(:func:`~torchiid.features.segmentation.graph_segmentation`) and adjacent regions are merged
greedily, most similar pair first, until one region is left. Every region of every hierarchy
(the initial ones included) is a proposal. The similarity is the sum of the selected terms

- ``c`` colour: histogram intersection of 25-bin-per-channel colour histograms (L1-normalised),
- ``t`` texture: histogram intersection of 10-bin histograms of half-wave rectified Gaussian
  derivatives (sigma = 1) in 8 orientations per channel (240 bins, L1-normalised),
- ``s`` size: ``1 - (|r_i| + |r_j|) / |image|`` (small regions merge first),
- ``f`` fill: ``1 - (|BB_ij| - |r_i| - |r_j|) / |image|`` (regions that fill each other's box).

**Scores.** Uijlings' randomised ranking: the regions of one hierarchy are numbered by creation
order from the top (the whole image is 1, the initial regions come last), each index is
multiplied by a uniform random number (seeded), and all proposals of all strategies are sorted
by that value (identical masks keep their best value). The score of the proposal of rank ``r``
(0-based) among ``P`` kept proposals is ``1 - r / P``, in ``(0, 1]``: large, late regions tend to
rank high. It plays the role of MCG's objectness score in ``g_i`` (see
:mod:`torchiid.features.midlevel`).

**Memory.** Proposals are not stored as ``P`` dense masks. Pixels that share their initial label
in *every* segmentation form an *atom*; each proposal is a union of atoms, so a set of proposals
is ``atom_labels (H, W)`` plus a boolean ``membership (A, P)``. :meth:`Proposals.masks` expands
masks on demand.

**Colour.** Tensor inputs are *linear* RGB (clipped to ``[0, 1]``) and are converted to sRGB
before segmentation, since Felzenszwalb's scale ``k`` and the histograms were designed for
display-referred values; numpy ``HxWx3`` inputs are taken as sRGB already (``uint8``, or float
in ``[0, 1]``, clipped).

**Modules.** This module holds the public API (:func:`selective_search`, :class:`Proposals`,
:class:`Strategy`) and the ranking; the colour spaces and histograms are in
:mod:`torchiid.features.proposal_features`, the regions and their hierarchical grouping in
:mod:`torchiid.features.proposal_grouping`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from torchiid.core.check import check_image
from torchiid.core.colour import linear_to_srgb_np as linear_to_srgb
from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.features.proposal_features import atom_histograms, to_colour_space
from torchiid.features.proposal_grouping import (
    adjacency,
    compact_labels,
    group_regions,
    intersect_segmentations,
    leaf_boxes,
    leaf_intervals,
)
from torchiid.features.segmentation import graph_segmentation

__all__ = ["COLOUR_SPACES", "Proposals", "Strategy", "selective_search", "linear_to_srgb"]

logger = logging.getLogger(__name__)

COLOUR_SPACES = ("rgb", "hsv", "lab")
MIN_SIDE = 8
_HASH_SEED = 0x5EED5EED


@dataclass(frozen=True)
class Strategy:
    """One selective-search strategy (a diversification choice of Uijlings et al.).

    Attributes:
        colour_space: ``"rgb"``, ``"hsv"`` or ``"lab"`` (each channel scaled to ``[0, 1]``).
        scale: Felzenszwalb's ``k`` (skimage's ``scale``, for values on a 0-255 scale).
        similarity: letters of ``"ctsf"`` (colour, texture, size, fill) summed in the similarity.
    """

    colour_space: str
    scale: float
    similarity: str


@dataclass(frozen=True, eq=False)
class Proposals:
    """Region proposals of one image, stored as unions of atoms.

    Attributes:
        atom_labels: ``(H, W)`` long, atom index of every pixel, in ``[0, A)``.
        membership: ``(A, P)`` bool, ``membership[a, p]`` is True when atom ``a`` lies in
            proposal ``p``.
        scores: ``(P,)`` float32 in ``(0, 1]``, decreasing with rank (proposal 0 ranks first).
        boxes: ``(P, 4)`` long ``x0, y0, x1, y1`` bounding boxes (``x1, y1`` exclusive).
        strategy: ``(P,)`` long, index into :attr:`strategies` of the hierarchy that produced
            the proposal (the best-ranked one when several produced the same mask).
        strategies: the strategies that were run.
    """

    atom_labels: torch.Tensor
    membership: torch.Tensor
    scores: torch.Tensor
    boxes: torch.Tensor
    strategy: torch.Tensor
    strategies: tuple[Strategy, ...]

    @property
    def num_proposals(self) -> int:
        """``P``, the number of proposals."""
        return int(self.membership.shape[1])

    @property
    def num_atoms(self) -> int:
        """``A``, the number of atoms."""
        return int(self.membership.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the image."""
        return int(self.atom_labels.shape[0]), int(self.atom_labels.shape[1])

    @cached_property
    def atom_sizes(self) -> torch.Tensor:
        """``(A,)`` long, pixel count of every atom."""
        return torch.bincount(self.atom_labels.reshape(-1), minlength=self.num_atoms)

    @cached_property
    def areas(self) -> torch.Tensor:
        """``(P,)`` long, pixel count of every proposal."""
        return (self.atom_sizes.unsqueeze(0).double() @ self.membership.double()).long()[0]

    def masks(self, indices: Sequence[int] | torch.Tensor | None = None) -> torch.Tensor:
        """Dense binary masks of the proposals ``indices`` (all when ``None``).

        Meant for tests and visualisation: the output holds ``P' * H * W`` bytes.

        Shape:
            - Output: ``(P', H, W)`` bool.
        """
        member = self.membership
        if indices is not None:
            idx = torch.as_tensor(indices, dtype=torch.long, device=member.device).reshape(-1)
            if idx.numel() and (
                int(idx.min()) < -self.num_proposals or int(idx.max()) >= self.num_proposals
            ):
                raise ParameterError(
                    f"proposal indices must lie in [0, {self.num_proposals}), "
                    f"got range [{int(idx.min())}, {int(idx.max())}]"
                )
            member = member[:, idx]
        return member[self.atom_labels].permute(2, 0, 1).contiguous()


def _as_srgb_arrays(image: torch.Tensor | np.ndarray) -> tuple[list[np.ndarray], bool]:
    """Validate the input; return float64 ``HxWx3`` sRGB arrays and whether it was batched."""
    if isinstance(image, np.ndarray):
        if image.ndim != 3 or image.shape[2] != 3:
            raise ShapeError(f"expected a numpy image of shape (H, W, 3), got {image.shape}")
        if image.dtype == np.uint8:
            arr = image.astype(np.float64) / 255.0
        elif np.issubdtype(image.dtype, np.floating):
            if not np.isfinite(image).all():
                raise ImageError("image contains NaN or infinite values")
            arr = np.clip(image.astype(np.float64), 0.0, 1.0)
        else:
            raise ShapeError(
                f"expected a uint8 or float numpy image (sRGB), got dtype {image.dtype}"
            )
        _check_side(arr.shape[0], arr.shape[1])
        return [arr], False
    if not isinstance(image, torch.Tensor):
        raise ShapeError(
            f"expected a torch.Tensor (3, H, W) / (B, 3, H, W) or a numpy (H, W, 3) image, "
            f"got {type(image).__name__}"
        )
    if image.dim() not in (3, 4):
        raise ShapeError(
            f"expected image of shape (3, H, W) or (B, 3, H, W), got {tuple(image.shape)}"
        )
    batched = image.dim() == 4
    x = image if batched else image.unsqueeze(0)
    check_image(x, "image", channels=3, min_side=MIN_SIDE)
    lin = x.detach().to("cpu", torch.float64).permute(0, 2, 3, 1).numpy()
    return [linear_to_srgb(im) for im in lin], batched


def _check_side(h: int, w: int) -> None:
    if h < MIN_SIDE or w < MIN_SIDE:
        raise ImageError(f"image is {w}x{h} px; at least {MIN_SIDE} px per side is needed")


def _validate(scales, colour_spaces, similarities, max_proposals, min_size, sigma) -> None:
    if len(scales) == 0 or any(not np.isfinite(k) or k <= 0 for k in scales):
        raise ParameterError(f"scales must be a non-empty list of positive numbers, got {scales}")
    bad = [c for c in colour_spaces if c not in COLOUR_SPACES]
    if len(colour_spaces) == 0 or bad:
        raise ParameterError(
            f"colour_spaces must be taken from {COLOUR_SPACES}, got {colour_spaces}"
        )
    if len(similarities) == 0 or any(not s or set(s) - set("ctsf") for s in similarities):
        raise ParameterError(
            f"similarities must be non-empty strings of the letters 'ctsf', got {similarities}"
        )
    if max_proposals is not None and int(max_proposals) < 1:
        raise ParameterError(f"max_proposals must be >= 1 or None, got {max_proposals}")
    if min_size is not None and int(min_size) < 1:
        raise ParameterError(f"min_size must be >= 1 or None, got {min_size}")
    if not sigma > 0:
        raise ParameterError(f"sigma must be > 0, got {sigma}")


def selective_search(
    image: torch.Tensor | np.ndarray,
    scales: Sequence[float] = (100.0,),
    colour_spaces: Sequence[str] = ("hsv", "lab"),
    similarities: Sequence[str] = ("ctsf", "tsf"),
    seed: int = 0,
    max_proposals: int | None = 2000,
    min_size: int | None = None,
    sigma: float = 0.8,
) -> Proposals | list[Proposals]:
    """Selective-search region proposals (masks with scores) of an image.

    One strategy is run for every combination of colour space, scale and similarity; the
    Felzenszwalb segmentation is shared by strategies that differ only in the similarity.
    Identical masks are merged; the ``max_proposals`` best-ranked are kept (see the module
    docstring for the ranking and the scores).

    Args:
        image: linear RGB tensor ``(3, H, W)`` or ``(B, 3, H, W)`` (values >= 0, clipped to 1),
            or an sRGB numpy array ``(H, W, 3)`` (``uint8``, or float in ``[0, 1]``).
        scales: Felzenszwalb ``k`` values (0-255 value scale, as in the original paper).
        colour_spaces: colour spaces of the segmentation and the histograms.
        similarities: similarity combinations, strings of ``"c"``, ``"t"``, ``"s"``, ``"f"``.
        seed: seed of the random ranking; the same seed gives the same output.
        max_proposals: keep at most this many proposals (``None``: keep all).
        min_size: Felzenszwalb's minimum component size; ``None`` uses ``k`` (Uijlings).
        sigma: Gaussian pre-smoothing of the Felzenszwalb segmentation.

    Returns:
        :class:`Proposals` (CPU tensors) for a single image; a list of them, one per image,
        for a ``(B, 3, H, W)`` batch.

    Raises:
        ShapeError: wrong type, rank, channel count or dtype.
        ImageError: image smaller than 8 px per side, NaN/inf or negative values.
        ParameterError: invalid parameters.

    Example:
        >>> img = torch.rand(3, 32, 48)
        >>> props = selective_search(img, scales=(50,), colour_spaces=("rgb",))
        >>> props.atom_labels.shape
        torch.Size([32, 48])
    """
    _validate(scales, colour_spaces, similarities, max_proposals, min_size, sigma)
    arrays, batched = _as_srgb_arrays(image)
    out = [
        _search_one(
            a,
            tuple(scales),
            tuple(colour_spaces),
            tuple(similarities),
            seed,
            max_proposals,
            min_size,
            sigma,
        )
        for a in arrays
    ]
    return out if batched else out[0]


def _search_one(
    srgb, scales, colour_spaces, similarities, seed, max_proposals, min_size, sigma
) -> Proposals:
    h, w, _ = srgb.shape
    converted = {cs: to_colour_space(srgb, cs) for cs in colour_spaces}
    seg_keys = [(cs, float(k)) for cs in colour_spaces for k in scales]

    def segment(key: tuple[str, float]) -> np.ndarray:
        cs, k = key
        ms = int(k) if min_size is None else int(min_size)
        seg = graph_segmentation(converted[cs], scale=k, sigma=sigma, min_size=max(ms, 1))
        return compact_labels(seg.reshape(-1), int(seg.max()) + 1).reshape(h, w)

    workers = min(len(seg_keys), torch.get_num_threads())
    if workers > 1:
        # OpenCV's segmentation releases the GIL: the strategies' segmentations run at once
        with ThreadPoolExecutor(workers) as pool:
            segs = list(pool.map(segment, seg_keys))
    else:
        segs = [segment(key) for key in seg_keys]
    atom_flat, rep = intersect_segmentations(segs)
    n_atoms = len(rep)
    atom_hist = {}
    for cs in colour_spaces:
        atom_hist[cs] = atom_histograms(converted[cs], atom_flat, n_atoms)
    atom_size = np.bincount(atom_flat, minlength=n_atoms)
    hash_rng = np.random.default_rng(_HASH_SEED)
    atom_hash = hash_rng.integers(0, np.iinfo(np.uint64).max, n_atoms, dtype=np.uint64)
    rng = np.random.default_rng(seed)

    strategies: list[Strategy] = []
    nodes = []  # per strategy: (segment index, lo, hi, sizes, boxes, rank value, hash)
    for si, ((cs, k), seg) in enumerate(zip(seg_keys, segs, strict=True)):
        r = int(seg.max()) + 1
        init = seg.reshape(-1)[rep]  # initial label of every atom
        nb = atom_hist[cs].shape[1]
        hist = np.bincount(
            (init[:, None] * nb + np.arange(nb)).ravel(),
            weights=atom_hist[cs].ravel(),
            minlength=r * nb,
        ).reshape(r, nb)
        size = np.bincount(init, weights=atom_size, minlength=r)
        box = leaf_boxes(seg, r)
        edges = adjacency(seg)
        leaf_hash = np.zeros(r, dtype=np.uint64)
        np.add.at(leaf_hash, init, atom_hash)
        for sim in similarities:
            children, sz, bx = group_regions(hist, size, box, edges, sim, h * w)
            lo, hi = leaf_intervals(children, r)
            prefix = np.zeros(r + 1, dtype=np.uint64)
            prefix[1:] = np.cumsum(leaf_hash[np.argsort(lo[:r])], dtype=np.uint64)
            node_hash = prefix[hi] - prefix[lo]
            n = len(sz)
            value = rng.random(n) * (n - np.arange(n))  # Uijlings: random x hierarchy index
            nodes.append((si, lo, hi, sz, bx, value, node_hash))
            strategies.append(Strategy(cs, k, sim))
    strat = np.concatenate([np.full(len(nd[3]), i) for i, nd in enumerate(nodes)])
    local = np.concatenate([np.arange(len(nd[3])) for nd in nodes])
    value = np.concatenate([nd[5] for nd in nodes])
    hsh = np.concatenate([nd[6] for nd in nodes])
    sizes = np.concatenate([nd[3] for nd in nodes])
    order = np.lexsort((value, sizes, hsh))  # group identical masks, best value first
    first = np.ones(len(order), dtype=bool)
    first[1:] = (hsh[order][1:] != hsh[order][:-1]) | (sizes[order][1:] != sizes[order][:-1])
    kept = order[first]
    kept = kept[np.argsort(value[kept], kind="stable")]
    if max_proposals is not None:
        kept = kept[: int(max_proposals)]
    p = len(kept)
    membership = np.zeros((n_atoms, p), dtype=bool)
    boxes = np.zeros((p, 4), dtype=np.int64)
    for i, (si, lo, hi, _, bx, _, _) in enumerate(nodes):
        cols = np.nonzero(strat[kept] == i)[0]
        if len(cols) == 0:
            continue
        idx = local[kept[cols]]
        pos = lo[segs[si].reshape(-1)[rep]]  # leaf position of every atom
        membership[:, cols] = (pos[:, None] >= lo[idx]) & (pos[:, None] < hi[idx])
        boxes[cols] = bx[idx].astype(np.int64)
    logger.debug(
        "selective search: %d strategies, %d atoms, %d proposals (of %d)",
        len(strategies),
        n_atoms,
        p,
        len(order),
    )
    return Proposals(
        atom_labels=torch.from_numpy(atom_flat.reshape(h, w)),
        membership=torch.from_numpy(membership),
        scores=torch.from_numpy(1.0 - np.arange(p, dtype=np.float32) / p),
        boxes=torch.from_numpy(boxes),
        strategy=torch.from_numpy(strat[kept].astype(np.int64)),
        strategies=tuple(strategies),
    )
