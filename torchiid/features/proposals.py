"""Selective-search object proposals as region masks (paper §3.1.2, DESIGN "Stage 0").

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
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
import scipy.ndimage as ndi
import torch

from torchiid.core.check import check_image
from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.features.segmentation import graph_segmentation

__all__ = ["COLOUR_SPACES", "Proposals", "Strategy", "selective_search", "linear_to_srgb"]

logger = logging.getLogger(__name__)

COLOUR_SPACES = ("rgb", "hsv", "lab")
MIN_SIDE = 8
_COLOUR_BINS = 25
_TEXTURE_BINS = 10
_ORIENTATIONS = 8
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


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Apply the sRGB transfer function (IEC 61966-2-1) to linear values clipped to ``[0, 1]``."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


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
        raise ImageError(f"image is {h}x{w} pixels; at least {MIN_SIDE} px per side is needed")


def _to_colour_space(srgb: np.ndarray, space: str) -> np.ndarray:
    """``HxWx3`` sRGB in ``[0, 1]`` to the colour space, every channel scaled to ``[0, 1]``.

    OpenCV's float conversions (D65 CIELab from sRGB; HSV with hue in degrees).
    """
    if space == "rgb":
        return srgb
    x = np.ascontiguousarray(srgb, dtype=np.float32)
    if space == "hsv":
        hsv = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)
        hsv[..., 0] /= 360.0
        return hsv.astype(np.float64)
    lab = cv2.cvtColor(x, cv2.COLOR_RGB2Lab).astype(np.float64)
    return np.stack(
        [lab[..., 0] / 100.0, (lab[..., 1] + 128.0) / 255.0, (lab[..., 2] + 128.0) / 255.0], -1
    ).clip(0.0, 1.0)


def _gaussian_derivatives(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d/dx, d/dy)`` of a float32 ``HxW`` image with Gaussian derivative filters, sigma 1."""
    u = np.arange(-4, 5, dtype=np.float32)
    g = np.exp(-0.5 * u * u)
    g /= g.sum()
    dg = u * g  # cv2 correlates: the kernel of d/du (G * I) is G'(-u) = u g(u)
    gx = cv2.sepFilter2D(x, -1, dg, g, borderType=cv2.BORDER_REFLECT)
    gy = cv2.sepFilter2D(x, -1, g, dg, borderType=cv2.BORDER_REFLECT)
    return gx, gy


def _atom_histograms(x: np.ndarray, atoms: np.ndarray, n_atoms: int) -> np.ndarray:
    """Colour and texture histogram counts of every atom, ``(A, 75 + 240)`` float64.

    Colour: 25 bins per channel of ``x`` (values in ``[0, 1]``). Texture: per channel and
    orientation ``o * 45`` degrees, the Gaussian derivative (sigma = 1) along that direction,
    half-wave rectified, scaled by the channel's largest response and cut into 10 bins (an
    orientation and its opposite share an axis: where one responds, the other is in bin 0).
    Computed one channel at a time, so memory stays ``O(H W)``.
    """
    xf = np.ascontiguousarray(x, dtype=np.float32)
    n_bins = 3 * _COLOUR_BINS + 3 * _ORIENTATIONS * _TEXTURE_BINS
    hist = np.zeros((n_atoms, n_bins))

    def add(base: int, q: np.ndarray, nb: int) -> None:
        counts = np.bincount(atoms * nb + q.reshape(-1), minlength=n_atoms * nb)
        hist[:, base : base + nb] += counts.reshape(n_atoms, nb)

    for c in range(3):
        q = np.minimum((xf[..., c] * _COLOUR_BINS).astype(np.int64), _COLOUR_BINS - 1)
        add(c * _COLOUR_BINS, q, _COLOUR_BINS)
    half = _ORIENTATIONS // 2
    theta = np.arange(half) * (np.pi / half)
    for c in range(3):
        gx, gy = _gaussian_derivatives(np.ascontiguousarray(xf[..., c]))
        d = [np.float32(np.cos(t)) * gx + np.float32(np.sin(t)) * gy for t in theta]
        scale = _TEXTURE_BINS / max(max(float(np.abs(di).max()) for di in d), 1e-12)
        for k, dk in enumerate(d):
            q = np.minimum((np.abs(dk) * scale).astype(np.int64), _TEXTURE_BINS - 1)
            base = 3 * _COLOUR_BINS + (c * _ORIENTATIONS + k) * _TEXTURE_BINS
            add(base, np.where(dk > 0, q, 0), _TEXTURE_BINS)
            add(base + half * _TEXTURE_BINS, np.where(dk < 0, q, 0), _TEXTURE_BINS)
    return hist


def _compact(key: np.ndarray, n_keys: int) -> np.ndarray:
    """Relabel non-negative ints to ``0 .. n_distinct - 1``, keeping their order."""
    if n_keys <= 1 << 26:  # a counting pass beats sorting
        present = np.bincount(key, minlength=n_keys) > 0
        return (np.cumsum(present) - 1)[key]
    return np.unique(key, return_inverse=True)[1].reshape(-1)


def _atoms(segs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Intersect segmentations: flat atom index ``(N,)`` and a pixel of each atom ``(A,)``."""
    key = segs[0].reshape(-1)
    for seg in segs[1:]:
        r = int(seg.max()) + 1
        key = _compact(key * r + seg.reshape(-1), (int(key.max()) + 1) * r)
    rep = np.empty(int(key.max()) + 1, dtype=np.int64)
    rep[key] = np.arange(key.size)
    return key, rep


def _adjacency(seg: np.ndarray) -> np.ndarray:
    """Unique unordered pairs ``(E, 2)`` of 4-adjacent distinct labels."""
    r = int(seg.max()) + 1
    a = np.concatenate([seg[:, :-1].ravel(), seg[:-1].ravel()])
    b = np.concatenate([seg[:, 1:].ravel(), seg[1:].ravel()])
    keep = a != b
    a, b = a[keep], b[keep]
    key = np.unique(np.minimum(a, b) * r + np.maximum(a, b))
    return np.stack([key // r, key % r], 1)


def _leaf_boxes(seg: np.ndarray, n: int) -> np.ndarray:
    """``(n, 4)`` float boxes ``x0, y0, x1, y1`` (exclusive ends) of labels ``0 .. n-1``."""
    sl = ndi.find_objects(seg + 1, max_label=n)
    return np.array([[s[1].start, s[0].start, s[1].stop, s[0].stop] for s in sl], np.float64)


def _group(
    hist: np.ndarray,
    size: np.ndarray,
    box: np.ndarray,
    edges: np.ndarray,
    similarity: str,
    n_pixels: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uijlings' hierarchical grouping of ``R`` initial regions.

    Args:
        hist: ``(R, 75 + 240)`` colour and texture histograms (counts).
        size: ``(R,)`` pixel counts.
        box: ``(R, 4)`` boxes.
        edges: ``(E, 2)`` adjacent pairs.
        similarity: letters of ``"ctsf"``.
        n_pixels: image size.

    Returns:
        ``children (M, 2)`` of the merged nodes ``R .. R + M - 1``, node ``sizes`` and
        ``boxes`` for all ``R + M`` nodes.
    """
    r = len(size)
    n = 2 * r - 1
    nc = 3 * _COLOUR_BINS
    hc = np.zeros((n, nc))
    ht = np.zeros((n, hist.shape[1] - nc))
    hc[:r] = hist[:, :nc] / hist[:, :nc].sum(1, keepdims=True)
    ht[:r] = hist[:, nc:] / hist[:, nc:].sum(1, keepdims=True)
    sz = np.zeros(n)
    sz[:r] = size
    bx = np.zeros((n, 4))
    bx[:r] = box
    use_c, use_t, use_s, use_f = (ch in similarity for ch in "ctsf")

    def sim(a: np.ndarray | int, b: np.ndarray) -> np.ndarray:
        s = np.zeros(len(b))
        if use_c:
            s += np.minimum(hc[a], hc[b]).sum(-1)
        if use_t:
            s += np.minimum(ht[a], ht[b]).sum(-1)
        if use_s:
            s += 1.0 - (sz[a] + sz[b]) / n_pixels
        if use_f:
            lo = np.minimum(bx[a, :2], bx[b, :2])
            hi = np.maximum(bx[a, 2:], bx[b, 2:])
            s += 1.0 - (np.prod(hi - lo, -1) - sz[a] - sz[b]) / n_pixels
        return s

    nbrs: list[set[int]] = [set() for _ in range(r)]
    for a, b in edges.tolist():
        nbrs[a].add(b)
        nbrs[b].add(a)
    s0 = sim(edges[:, 0], edges[:, 1]) if len(edges) else np.zeros(0)
    heap = list(zip((-s0).tolist(), edges[:, 0].tolist(), edges[:, 1].tolist(), strict=True))
    heapq.heapify(heap)
    alive = [True] * r
    children = []
    t = r
    while heap:
        _, a, b = heapq.heappop(heap)
        if not (alive[a] and alive[b]):
            continue
        sa, sb = sz[a], sz[b]
        sz[t] = sa + sb
        hc[t] = (sa * hc[a] + sb * hc[b]) / sz[t]
        ht[t] = (sa * ht[a] + sb * ht[b]) / sz[t]
        bx[t, :2] = np.minimum(bx[a, :2], bx[b, :2])
        bx[t, 2:] = np.maximum(bx[a, 2:], bx[b, 2:])
        alive[a] = alive[b] = False
        alive.append(True)
        nb = (nbrs[a] | nbrs[b]) - {a, b}
        for m in nb:
            nbrs[m].discard(a)
            nbrs[m].discard(b)
            nbrs[m].add(t)
        nbrs.append(nb)
        nbrs[a] = nbrs[b] = set()
        if nb:
            arr = np.fromiter(nb, dtype=np.int64, count=len(nb))
            for s, m in zip(sim(t, arr).tolist(), arr.tolist(), strict=True):
                heapq.heappush(heap, (-s, m, t))
        children.append((a, b))
        t += 1
    ch = np.array(children, dtype=np.int64).reshape(-1, 2)
    return ch, sz[:t], bx[:t]


def _leaf_intervals(children: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
    """Order leaves so that every node is a contiguous range ``[lo, hi)`` of leaf positions."""
    n = r + len(children)
    cnt = np.ones(n, dtype=np.int64)
    parent = np.full(n, -1, dtype=np.int64)
    ch = children.tolist()
    for m, (a, b) in enumerate(ch):
        cnt[r + m] = cnt[a] + cnt[b]
        parent[a] = parent[b] = r + m
    lo = np.zeros(n, dtype=np.int64)
    start = 0
    for root in np.nonzero(parent < 0)[0].tolist():  # one root unless the graph is split
        lo[root] = start
        start += int(cnt[root])
    for m in range(len(ch) - 1, -1, -1):
        a, b = ch[m]
        lo[a] = lo[r + m]
        lo[b] = lo[r + m] + cnt[a]
    return lo, lo + cnt


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
    converted = {cs: _to_colour_space(srgb, cs) for cs in colour_spaces}
    seg_keys = [(cs, float(k)) for cs in colour_spaces for k in scales]
    segs = []
    for cs, k in seg_keys:
        ms = int(k) if min_size is None else int(min_size)
        seg = graph_segmentation(converted[cs], scale=k, sigma=sigma, min_size=max(ms, 1))
        segs.append(_compact(seg.reshape(-1), int(seg.max()) + 1).reshape(h, w))
    atom_flat, rep = _atoms(segs)
    n_atoms = len(rep)
    atom_hist = {}
    for cs in colour_spaces:
        atom_hist[cs] = _atom_histograms(converted[cs], atom_flat, n_atoms)
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
        box = _leaf_boxes(seg, r)
        edges = _adjacency(seg)
        leaf_hash = np.zeros(r, dtype=np.uint64)
        np.add.at(leaf_hash, init, atom_hash)
        for sim in similarities:
            children, sz, bx = _group(hist, size, box, edges, sim, h * w)
            lo, hi = _leaf_intervals(children, r)
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
