"""Per-pixel mid-level features ``g_i`` from region proposals (paper §3.1.2, Fig. 3).

``g_i`` is the vector, over all ``P`` proposals, of the proposal's mask value at pixel ``i``
times the proposal's score, L2-normalised: ``g_i = (m_ip s_p)_p / ||(m_ip s_p)_p||``. The
mid-level shading prior ``S_m`` (Eq. 4) weighs 3x3 neighbours by
``exp(-(1 - <g_i, g_j>)^2 / t_m^2)``; the reflectance prior ``B`` (Eq. 9) uses PCA-reduced
features ``g̊``.

Proposals are unions of *atoms* (see :mod:`torchiid.features.proposals`), so ``g`` is constant
on every atom and is stored per atom, ``atom_g (A, P)``. Pixels covered by no proposal get the
zero vector (their similarity with every pixel, themselves included, is 0; with the default
selective search every pixel is covered, since the whole image is a proposal). The PCA is
computed over *pixels* (atoms weighted by their pixel counts) and keeps distances (no whitening):
``||g̊_i - g̊_j||^2 <= ||g_i - g_j||^2 = 2 - 2 <g_i, g_j>``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.features.proposals import Proposals
from torchiid.priors.stencil import Stencil

__all__ = ["MidLevelBatch", "MidLevelFeatures", "midlevel_features", "midlevel_features_batch"]

logger = logging.getLogger(__name__)

_EXACT_PCA_LIMIT = 512
_POWER_ITERATIONS = 5
_CHUNK = 1 << 22  # elements per chunk of pair products


@dataclass(frozen=True, eq=False)
class MidLevelFeatures:
    """Mid-level features ``g_i`` of one image, stored per atom.

    Attributes:
        atom_labels: ``(H, W)`` long atom index of every pixel.
        atom_g: ``(A, P)`` float, unit-norm rows (zero rows for uncovered atoms).
        atom_sizes: ``(A,)`` long pixel count of every atom.
    """

    atom_labels: torch.Tensor
    atom_g: torch.Tensor
    atom_sizes: torch.Tensor
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return int(self.atom_labels.shape[0]), int(self.atom_labels.shape[1])

    @property
    def num_proposals(self) -> int:
        """``P``, the length of ``g_i``."""
        return int(self.atom_g.shape[1])

    @property
    def covered(self) -> torch.Tensor:
        """``(A,)`` bool: the atom lies in at least one proposal (its ``g`` has norm 1)."""
        return self.atom_g.abs().amax(dim=1) > 0

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> MidLevelFeatures:
        """A copy on ``device`` with ``atom_g`` in ``dtype`` (floating)."""
        return MidLevelFeatures(
            self.atom_labels.to(device), self.atom_g.to(device, dtype), self.atom_sizes.to(device)
        )

    def dense(self) -> torch.Tensor:
        """All of ``g`` per pixel; ``P * H * W`` values, for tests and small images.

        Shape:
            - Output: ``(1, P, H, W)``.
        """
        return self.atom_g[self.atom_labels].permute(2, 0, 1).unsqueeze(0)

    def pca_atoms(self, dim: int = 8, method: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel-weighted PCA of ``g`` projected per atom.

        Args:
            dim: number of components ``d``.
            method: ``"exact"`` (eigendecomposition of the smaller Gram matrix),
                ``"randomized"`` (seeded subspace iteration, Halko et al. 2011) or ``"auto"``
                (exact when ``min(A, P) <= 512``).

        Returns:
            ``(projections (A, d), variances (d,))``: centred projections of every atom on the
            components (sorted by decreasing variance ``variances``). Sign convention: the
            largest-magnitude entry of every component vector is positive.
        """
        if not isinstance(dim, int) or dim < 1 or dim > self.num_proposals:
            raise ParameterError(
                f"PCA dim must be an int in [1, P = {self.num_proposals}], got {dim!r}"
            )
        if method not in ("auto", "exact", "randomized"):
            raise ParameterError(f"method must be 'auto', 'exact' or 'randomized', got {method!r}")
        a, p = self.atom_g.shape
        if method == "auto":
            method = "exact" if min(a, p) <= _EXACT_PCA_LIMIT else "randomized"
        key = ("pca", dim, method)
        if key not in self._cache:
            self._cache[key] = _weighted_pca(self.atom_g, self.atom_sizes, dim, method)
        return self._cache[key]

    def pca(self, dim: int = 8, method: str = "auto") -> torch.Tensor:
        """PCA-reduced features ``g̊`` per pixel (used by the reflectance prior, Eq. 9).

        See :meth:`pca_atoms` for the arguments.

        Shape:
            - Output: ``(1, d, H, W)``, dtype and device of ``atom_g``.
        """
        proj, _ = self.pca_atoms(dim, method)
        return proj[self.atom_labels].permute(2, 0, 1).unsqueeze(0)

    def similarity(self, stencil: Stencil) -> torch.Tensor:
        """``<g_i, g_j>`` for every stencil pair ``(i, i + offset_k)`` (Eq. 4's ``S_m`` weights).

        Pairs outside the image are 0; pairs inside one atom are exactly 1 (0 if uncovered).
        Computed once per distinct pair of adjacent atoms.

        Shape:
            - Output: ``(1, K, H, W)``, dtype and device of ``atom_g``.
        """
        h, w = self.shape
        if (stencil.height, stencil.width) != (h, w):
            raise ShapeError(
                f"stencil is {stencil.height}x{stencil.width} but the features are {h}x{w}"
            )
        g = self.atom_g
        n_atoms = g.shape[0]
        labels = self.atom_labels.to(g.device)
        cover = self.covered.to(g.dtype)
        views = [_pair_views(labels, dy, dx) for dy, dx in stencil.offsets]
        keys = []
        for a, b in views:
            diff = a != b
            keys.append((torch.minimum(a, b) * n_atoms + torch.maximum(a, b))[diff])
        uniq = torch.unique(torch.cat(keys))
        dots = torch.cat([_pair_dots(g, uniq // n_atoms, uniq % n_atoms), g.new_zeros(1)])
        out = torch.zeros(1, len(views), h, w, dtype=g.dtype, device=g.device)
        for k, (dy, dx) in enumerate(stencil.offsets):
            a, b = views[k]
            idx = torch.searchsorted(uniq, torch.minimum(a, b) * n_atoms + torch.maximum(a, b))
            ys, xs = _first_slices(dy, dx, h, w)
            out[0, k, ys, xs] = torch.where(a != b, dots[idx], cover[a])
        return out


def _first_slices(dy: int, dx: int, h: int, w: int) -> tuple[slice, slice]:
    """Rows and columns of the pixels ``i`` whose partner ``i + (dy, dx)`` is in the image."""
    return slice(max(0, -dy), h - max(0, dy)), slice(max(0, -dx), w - max(0, dx))


def _pair_views(labels: torch.Tensor, dy: int, dx: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Labels of the first and second pixel of every valid pair of offset ``(dy, dx)``."""
    h, w = labels.shape
    ys, xs = _first_slices(dy, dx, h, w)
    yj = slice(ys.start + dy, ys.stop + dy)
    xj = slice(xs.start + dx, xs.stop + dx)
    return labels[ys, xs], labels[yj, xj]


def _pair_dots(g: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``(g[a] * g[b]).sum(1)`` in chunks that bound memory."""
    out = torch.empty(a.shape, dtype=g.dtype, device=g.device)
    step = max(1, _CHUNK // max(1, g.shape[1]))
    for s in range(0, a.numel(), step):
        out[s : s + step] = (g[a[s : s + step]] * g[b[s : s + step]]).sum(1)
    return out


def _weighted_pca(
    g: torch.Tensor, sizes: torch.Tensor, dim: int, method: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-weighted PCA of atom rows; returns ``(A, d)`` projections and ``(d,)`` variances."""
    w = sizes.to(g.dtype)
    sw = (w / w.sum()).sqrt().unsqueeze(1)  # Y = sw * (g - mu): covariance = Y^T Y
    mu = (w / w.sum()) @ g
    a, p = g.shape
    if method == "exact":
        g64, sw64, mu64 = g.double(), sw.double(), mu.double()
        y = sw64 * (g64 - mu64)
        if p <= a:
            evals, evecs = torch.linalg.eigh(y.T @ y)
            evals, v = evals.flip(0)[:dim], evecs.flip(1)[:, :dim]
        else:
            evals, u = torch.linalg.eigh(y @ y.T)
            evals, u = evals.flip(0)[:dim], u.flip(1)[:, :dim]
            pos = evals > evals.max().clamp_min(0) * 1e-12
            v = (y.T @ u) / evals.clamp_min(1e-300).sqrt()
            v = v * pos.to(v.dtype)
        evals = evals.clamp_min(0)
    else:
        q = min(dim + 10, a, p)
        gen = torch.Generator(device="cpu").manual_seed(0)
        omega = torch.randn(p, q, generator=gen, dtype=g.dtype).to(g.device)

        def ymul(z: torch.Tensor) -> torch.Tensor:  # Y z, (A, q)
            return sw * (g @ z - mu @ z)

        def ytmul(z: torch.Tensor) -> torch.Tensor:  # Y^T z, (P, q)
            return g.T @ (sw * z) - torch.outer(mu, sw[:, 0] @ z)

        basis = torch.linalg.qr(ymul(omega)).Q
        for _ in range(_POWER_ITERATIONS):
            basis = torch.linalg.qr(ymul(torch.linalg.qr(ytmul(basis)).Q)).Q
        _, s, vt = torch.linalg.svd(ytmul(basis).T.double(), full_matrices=False)
        v = vt[:dim].T
        evals = s[:dim] ** 2
    if v.shape[1] < dim:  # fewer atoms than components: pad with zero components
        v = torch.cat([v, v.new_zeros(p, dim - v.shape[1])], 1)
        evals = torch.cat([evals, evals.new_zeros(dim - evals.numel())])
    idx = v.abs().argmax(0)
    sign = torch.sign(v[idx, torch.arange(dim, device=v.device)])
    v = v * torch.where(sign == 0, torch.ones_like(sign), sign)
    v = v.to(g.dtype)
    return (g - mu) @ v, evals.to(g.dtype)


def midlevel_features(
    proposals: Proposals,
    like: torch.Tensor | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> MidLevelFeatures:
    """Mid-level features ``g_i`` (paper §3.1.2) of one image's proposals.

    Args:
        proposals: the proposals of the image (:func:`~torchiid.features.selective_search`).
        like: reference tensor whose dtype and device the features take.
        dtype: floating dtype (overrides ``like``; default float32).
        device: device (overrides ``like``; default the proposals' device).

    Returns:
        :class:`MidLevelFeatures`; ``atom_g[a] = m_a * s / ||m_a * s||`` with ``m_a`` the atom's
        proposal memberships and ``s`` the scores (zero rows for uncovered atoms).

    Example:
        >>> from torchiid.features.proposals import selective_search
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> mid = midlevel_features(selective_search(torch.rand(3, 32, 48), scales=(50,)))
        >>> mid.pca(8).shape
        torch.Size([1, 8, 32, 48])
    """
    if not isinstance(proposals, Proposals):
        raise ShapeError(f"expected Proposals, got {type(proposals).__name__}")
    dtype = dtype or (like.dtype if like is not None else torch.float32)
    if not dtype.is_floating_point:
        raise ParameterError(f"expected a floating dtype, got {dtype}")
    device = (
        device
        if device is not None
        else (like.device if like is not None else proposals.membership.device)
    )
    member = proposals.membership.to(device)
    g = member.to(dtype) * proposals.scores.to(device, dtype)
    norm = torch.linalg.vector_norm(g, dim=1, keepdim=True)
    g = torch.where(norm > 0, g / norm.clamp_min(torch.finfo(dtype).tiny), g)
    return MidLevelFeatures(proposals.atom_labels.to(device), g, proposals.atom_sizes.to(device))


@dataclass(frozen=True)
class MidLevelBatch:
    """Mid-level features of ``B`` images of one size ``H x W``, with ``(B, ...)`` outputs.

    Every image keeps its own proposals and its own PCA. Index or iterate to get the
    per-image :class:`MidLevelFeatures`.
    """

    items: tuple[MidLevelFeatures, ...]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> MidLevelFeatures:
        return self.items[i]

    def __iter__(self) -> Iterator[MidLevelFeatures]:
        return iter(self.items)

    def pca(self, dim: int = 8, method: str = "auto") -> torch.Tensor:
        """Per-image PCA features, ``(B, d, H, W)``."""
        return torch.cat([m.pca(dim, method) for m in self.items])

    def similarity(self, stencil: Stencil) -> torch.Tensor:
        """Per-image stencil similarities, ``(B, K, H, W)``."""
        return torch.cat([m.similarity(stencil) for m in self.items])


def midlevel_features_batch(
    proposals: Sequence[Proposals],
    like: torch.Tensor | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> MidLevelBatch:
    """:func:`midlevel_features` of several images of the same size (e.g. a batch's proposals).

    Raises:
        ShapeError: empty list, or images of different sizes.
    """
    items = tuple(midlevel_features(p, like, dtype, device) for p in proposals)
    if not items:
        raise ShapeError("expected at least one Proposals, got an empty sequence")
    sizes = {m.shape for m in items}
    if len(sizes) > 1:
        raise ShapeError(f"all images of a batch must have the same (H, W), got {sorted(sizes)}")
    return MidLevelBatch(items)
