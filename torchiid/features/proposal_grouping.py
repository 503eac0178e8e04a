"""Regions of selective search and their hierarchical grouping (Uijlings et al. 2013).

The segmentations of all strategies are intersected into *atoms* (:func:`intersect_segmentations`);
each strategy's initial regions are grouped greedily, most similar adjacent pair first, into a
binary hierarchy (:func:`group_regions`), whose nodes are contiguous ranges of a leaf order
(:func:`leaf_intervals`), so a proposal is a range test on the atoms' leaf positions.
"""

from __future__ import annotations

import heapq

import numpy as np
import torch

from torchiid.features.proposal_features import NUM_COLOUR_HIST_BINS

__all__ = [
    "compact_labels",
    "intersect_segmentations",
    "adjacency",
    "leaf_boxes",
    "group_regions",
    "leaf_intervals",
]


def compact_labels(key: np.ndarray, n_keys: int) -> np.ndarray:
    """Relabel non-negative ints to ``0 .. n_distinct - 1``, keeping their order."""
    if n_keys <= 1 << 26:  # a counting pass beats sorting
        present = np.bincount(key, minlength=n_keys) > 0
        return (np.cumsum(present, dtype=np.int64) - 1)[key]
    return np.unique(key, return_inverse=True)[1].reshape(-1)


def intersect_segmentations(segs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Intersect segmentations: flat atom index ``(N,)`` and a pixel of each atom ``(A,)``."""
    key = segs[0].reshape(-1)
    for seg in segs[1:]:
        r = int(seg.max()) + 1
        key = compact_labels(key * r + seg.reshape(-1), (int(key.max()) + 1) * r)
    rep = np.empty(int(key.max()) + 1, dtype=np.int64)
    rep[key] = np.arange(key.size)
    return key, rep


def adjacency(seg: np.ndarray) -> np.ndarray:
    """Unique unordered pairs ``(E, 2)`` of 4-adjacent distinct labels."""
    r = int(seg.max()) + 1
    a = np.concatenate([seg[:, :-1].ravel(), seg[:-1].ravel()])
    b = np.concatenate([seg[:, 1:].ravel(), seg[1:].ravel()])
    keep = a != b
    a, b = a[keep], b[keep]
    key = np.unique(np.minimum(a, b) * r + np.maximum(a, b))
    return np.stack([key // r, key % r], 1)


def leaf_boxes(seg: np.ndarray, n: int) -> np.ndarray:
    """``(n, 4)`` float boxes ``x0, y0, x1, y1`` (exclusive ends) of labels ``0 .. n-1``.

    Every label must occur in ``seg``. The extremes come from scatter reductions over the
    pixels in torch, which the process has loaded anyway (``scipy.ndimage.find_objects``
    does the same but costs its import, a tenth of a second, at every start).
    """
    h, w = seg.shape
    labels = torch.from_numpy(np.ascontiguousarray(seg, dtype=np.int64)).reshape(-1)
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= n):
        raise ValueError(f"labels must lie in 0 .. {n - 1}")
    ys = torch.arange(h).repeat_interleave(w)
    xs = torch.arange(w).repeat(h)

    def extreme(coords: torch.Tensor, how: str) -> torch.Tensor:
        return torch.zeros(n, dtype=torch.int64).scatter_reduce_(
            0, labels, coords, how, include_self=False
        )

    low = [extreme(xs, "amin"), extreme(ys, "amin")]
    high = [extreme(xs, "amax") + 1, extreme(ys, "amax") + 1]
    return torch.stack(low + high, dim=1).numpy().astype(np.float64)


def group_regions(
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
    nc = NUM_COLOUR_HIST_BINS
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


def leaf_intervals(children: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
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
