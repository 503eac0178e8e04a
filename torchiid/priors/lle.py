"""The LLE neighbourhood-consistency term ``S_c`` (paper Eq. 2).

Every patch ``b`` (its centre pixel stands for the patch) is approximated as an affine
combination of ``k`` other patches ``N_b`` (default 10) chosen in feature space:
``S_c = sum_b (s_b - sum_{a in N_b} w_ab s_a)^2`` on the log-shading ``s``. The weights are
Roweis & Saul's LLE weights: with ``Z = [f_a - f_b]_{a in N_b}`` and ``C = Z Z^T``, solve
``(C + reg * tr(C) * I) w = 1`` and normalise ``sum_a w_ab = 1`` (so the rows annihilate constants).

Strategies of paper Table 2: features are the CNN features ``f_b`` ("cnn") or the patch's mean
RGB colour ("rgb", :func:`patch_rgb_features`); neighbours are the kNN in feature space
("knn") or ``k`` random other patches ("random", seeded):
p1 = rgb + knn, p2 = rgb + random, p3 = cnn + random, p4 = cnn + knn (the paper's best).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchiid.core.cache import InputKey, input_key
from torchiid.core.check import check_finite, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.pairs import constraint_matrix
from torchiid.priors.quadratic import ConstraintQuadratic

__all__ = [
    "select_neighbours",
    "lle_weights",
    "patch_rgb_features",
    "lle_term",
    "LLENeighbourhood",
    "STRATEGIES",
]

#: Paper Table 2: strategy -> (feature type, neighbour choice).
STRATEGIES = {
    "p1": ("rgb", "knn"),
    "p2": ("rgb", "random"),
    "p3": ("cnn", "random"),
    "p4": ("cnn", "knn"),
}


def _batched_centers(centers: torch.Tensor, batch: int) -> torch.Tensor:
    if centers.dim() == 2:
        centers = centers.unsqueeze(0).expand(batch, -1, -1)
    if centers.dim() != 3 or centers.shape[-1] != 2 or centers.shape[0] != batch:
        raise ShapeError(
            f"expected patch centres (P, 2) or ({batch}, P, 2) as (y, x), "
            f"got {tuple(centers.shape)}"
        )
    if centers.is_floating_point():
        raise ShapeError(f"patch centres must be integer pixel coordinates, got {centers.dtype}")
    return centers.long()


def select_neighbours(
    features: torch.Tensor,
    k: int = 10,
    strategy: str = "knn",
    valid: torch.Tensor | None = None,
    seed: int = 0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick ``k`` neighbours of every patch, never itself.

    Args:
        features: ``(B, P, D)`` patch features.
        k: neighbours per patch; fewer are used when fewer valid patches exist.
        strategy: ``"knn"`` (Euclidean nearest in feature space) or ``"random"``.
        valid: optional ``(B, P)`` bool; invalid patches are never chosen.
        seed: seed of the ``"random"`` strategy (private generator).

    Returns:
        ``(index (B, P, k'), ok (B, P, k'))`` with ``k' = min(k, P - 1)``; ``ok`` is False where
        no valid neighbour was left.
    """
    b, p, _ = features.shape
    if k < 1:
        raise ParameterError(f"k must be >= 1, got {k}")
    if p < 2:
        raise ParameterError(f"LLE needs at least 2 patches, got {p}")
    kk = min(k, p - 1)
    if strategy == "knn":
        score = torch.cdist(features.double(), features.double())
    elif strategy == "random":
        g = torch.Generator().manual_seed(seed)
        score = torch.rand(b, p, p, generator=g, dtype=torch.float64).to(features.device)
    else:
        raise ParameterError(f"strategy must be 'knn' or 'random', got {strategy!r}")
    eye = torch.eye(p, dtype=torch.bool, device=features.device)
    bad = eye.unsqueeze(0).expand(b, p, p)
    if valid is not None:
        bad = bad | ~valid.unsqueeze(1)
    score = score.masked_fill(bad, float("inf"))
    val, idx = torch.topk(score, kk, dim=2, largest=False)
    return idx, torch.isfinite(val)


def lle_weights(
    features: torch.Tensor,
    index: torch.Tensor,
    ok: torch.Tensor | None = None,
    reg: float = 1e-3,
) -> torch.Tensor:
    """LLE reconstruction weights of every patch over its neighbours (float64 inside).

    Args:
        features: ``(B, P, D)``.
        index: ``(B, P, k)`` neighbour indices.
        ok: optional ``(B, P, k)`` bool; False neighbours get weight 0.
        reg: Gram regulariser, ``C + reg * tr(C) * I`` (paper: 1e-3).

    Returns:
        ``(B, P, k)`` weights in the features' dtype, each row summing to 1 (rows without any
        ok neighbour are all 0).
    """
    if reg < 0:
        raise ParameterError(f"reg must be >= 0, got {reg}")
    f = features.double()
    b, p, d = f.shape
    kk = index.shape[-1]
    ok = torch.ones_like(index, dtype=torch.bool) if ok is None else ok
    nb = torch.gather(
        f.unsqueeze(1).expand(b, p, p, d), 2, index.unsqueeze(-1).expand(-1, -1, -1, d)
    )
    z = (nb - f.unsqueeze(2)) * ok.unsqueeze(-1)  # (B, P, k, D)
    c = z @ z.transpose(-1, -2)
    tr = c.diagonal(dim1=-2, dim2=-1).sum(-1, keepdim=True)  # (B, P, 1)
    lam = reg * tr
    lam = torch.where(lam > 0, lam, torch.ones_like(lam))  # identical features: uniform weights
    eye = torch.eye(kk, dtype=torch.float64, device=f.device)
    okf = ok.double()
    pair_ok = okf.unsqueeze(-1) * okf.unsqueeze(-2)
    c = c * pair_ok + eye * (lam.unsqueeze(-1) * pair_ok + (1 - okf).unsqueeze(-1))
    w = torch.linalg.solve(c, okf)
    s = w.sum(-1, keepdim=True)
    w = torch.where(s.abs() > 0, w / torch.where(s.abs() > 0, s, 1), torch.zeros_like(w))
    return w.to(features.dtype)


def patch_rgb_features(
    image: torch.Tensor, centers: torch.Tensor, patch_size: int = 60
) -> torch.Tensor:
    """Mean colour of each ``patch_size`` square around its centre (clipped at the borders).

    The "RGB" feature of paper Table 2 (strategies p1, p2), via an integral image.

    Shape:
        image ``(B, C, H, W)``, centres ``(P, 2)`` or ``(B, P, 2)`` (y, x) -> ``(B, P, C)``.
    """
    b, c, h, w = image.shape
    ctr = _batched_centers(centers, b)
    half = patch_size // 2
    ii = torch.nn.functional.pad(image.double().cumsum(2).cumsum(3), (1, 0, 1, 0))
    y0 = (ctr[..., 0] - half).clamp(0, h)
    y1 = (ctr[..., 0] - half + patch_size).clamp(0, h)
    x0 = (ctr[..., 1] - half).clamp(0, w)
    x1 = (ctr[..., 1] - half + patch_size).clamp(0, w)
    flat = ii.flatten(2)  # (B, C, (H+1)(W+1))

    def at(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return torch.gather(flat, 2, (y * (w + 1) + x).unsqueeze(1).expand(b, c, -1))

    s = at(y1, x1) - at(y0, x1) - at(y1, x0) + at(y0, x0)
    area = ((y1 - y0) * (x1 - x0)).clamp_min(1).unsqueeze(1)
    return (s / area).transpose(1, 2).to(image.dtype)


@dataclass
class LLENeighbourhood:
    """The last neighbours and LLE weights :func:`lle_term` computed, for reuse.

    An entry is reused when the features are the same tensor (unmodified), the options are
    the same and the same patches are valid (both all, or equal ``valid`` masks); the
    result is then what the call would have computed.

    Attributes:
        hits: how many computations were skipped.
    """

    key: InputKey | None = None
    valid: torch.Tensor | None = None
    index: torch.Tensor | None = None
    ok: torch.Tensor | None = None
    weights: torch.Tensor | None = None
    hits: int = 0

    def matches(self, key: InputKey, valid: torch.Tensor | None) -> bool:
        """Whether the stored entry is the one for ``key`` and ``valid``."""
        if self.key is None or not self.key == key:
            return False
        if valid is None or self.valid is None:
            return valid is None and self.valid is None
        return valid.shape == self.valid.shape and bool(torch.equal(valid, self.valid))

    def lookup(
        self, key: InputKey, valid: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The stored ``(index, ok, weights)`` when they are the ones for ``key`` and ``valid``."""
        if not self.matches(key, valid):
            return None
        if self.index is None or self.ok is None or self.weights is None:
            return None
        self.hits += 1
        return self.index, self.ok, self.weights

    def store(
        self,
        key: InputKey,
        valid: torch.Tensor | None,
        index: torch.Tensor,
        ok: torch.Tensor,
        weights: torch.Tensor,
    ) -> None:
        """Keep this computation's result."""
        self.key, self.valid, self.index, self.ok, self.weights = key, valid, index, ok, weights


def lle_term(
    centers: torch.Tensor,
    features: torch.Tensor,
    height: int,
    width: int,
    k: int = 10,
    reg: float = 1e-3,
    neighbours: str = "knn",
    mask: torch.Tensor | None = None,
    seed: int = 0,
    reuse: LLENeighbourhood | None = None,
) -> ConstraintQuadratic:
    """The consistency term ``S_c`` (Eq. 2): one row ``s_b - sum_a w_ab s_a`` per patch centre.

    Args:
        centers: ``(P, 2)`` or ``(B, P, 2)`` integer ``(y, x)`` patch centres.
        features: ``(B, P, D)`` patch features (``f_b``, or :func:`patch_rgb_features`).
        height: image height.
        width: image width.
        k: neighbours per patch (paper: 10).
        reg: Gram regulariser (paper: 1e-3).
        neighbours: ``"knn"`` or ``"random"`` (paper Table 2).
        mask: optional ``(B, 1, H, W)`` bool; patches centred outside it are neither
            constrained nor used as neighbours.
        seed: seed of the random strategy.
        reuse: an :class:`LLENeighbourhood` that keeps the neighbours and weights between
            calls: they depend on the features, the options and which patches are valid, not
            on the image size, so the coarse-to-fine shading solve computes them once for its
            levels.

    Returns:
        :class:`~torchiid.priors.quadratic.ConstraintQuadratic` on ``(B, 1, H, W)``, in the
        features' dtype and device.

    Raises:
        ShapeError: inconsistent shapes. ImageError: non-finite features.
        ParameterError: fewer than 2 patches, centres outside the image, bad options.
    """
    if features.dim() != 3:
        raise ShapeError(f"expected patch features (B, P, D), got {tuple(features.shape)}")
    b, p, _ = features.shape
    ctr = _batched_centers(centers, b)
    if ctr.shape[1] != p:
        raise ShapeError(f"{ctr.shape[1]} patch centres but {p} feature vectors")
    check_finite(features, "patch features")
    if bool((ctr[..., 0] < 0).any() | (ctr[..., 0] >= height).any()) or bool(
        (ctr[..., 1] < 0).any() | (ctr[..., 1] >= width).any()
    ):
        raise ParameterError(f"patch centres must lie inside the {height}x{width} image")
    pix = ctr[..., 0] * width + ctr[..., 1]  # (B, P)
    valid = None
    if mask is not None:
        check_shape(mask, (b, 1, height, width), "mask")
        valid = torch.gather(mask.reshape(b, -1), 1, pix)
    key = input_key(features, k, reg, neighbours, seed)
    found = None if reuse is None else reuse.lookup(key, valid)
    if found is not None:
        idx, ok, w = found
    else:
        idx, ok = select_neighbours(features, k, neighbours, valid, seed)
        w = lle_weights(features, idx, ok, reg)
        if reuse is not None:
            reuse.store(key, valid, idx, ok, w)
    row_ok = ok.any(-1) if valid is None else ok.any(-1) & valid
    kk = idx.shape[-1]
    nb_pix = torch.gather(pix, 1, idx.reshape(b, -1)).view(b, p, kk)
    rows = torch.arange(p, device=features.device).view(1, p, 1).expand(b, p, kk + 1)
    cols = torch.cat([pix.unsqueeze(-1), nb_pix], dim=-1)
    vals = torch.cat([torch.ones_like(w[..., :1]), -w], dim=-1) * row_ok.unsqueeze(-1).to(w.dtype)
    m = constraint_matrix(
        rows.reshape(b, -1), cols.reshape(b, -1), vals.reshape(b, -1), p, height, width
    )
    return ConstraintQuadratic(m, (b, 1, height, width))
