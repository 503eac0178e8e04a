"""Hierarchical sparsify-and-compensate preconditioner (Krishnan, Fattal & Szeliski 2013)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from torchiid.solvers.dense import DenseSPD
from torchiid.solvers.system import CSRPreconditioner

__all__ = ["HSCPreconditioner"]

#: a level's elimination: fine nodes, coarse nodes, ``1 / D_F`` and the C-F edge weights
_Elimination = tuple[np.ndarray, np.ndarray, np.ndarray, Any]


def _edges(coo: Any, keep: np.ndarray, shape: tuple[int, int]) -> Any:
    """The symmetric matrix of the kept upper-triangle edges of ``coo`` (scipy CSR)."""
    import scipy.sparse as sp

    rows, cols, data = coo.row[keep], coo.col[keep], coo.data[keep]
    ij = (np.concatenate([rows, cols]), np.concatenate([cols, rows]))
    return sp.csr_matrix((np.concatenate([data, data]), ij), shape=shape)


def _compensate(w: Any, drop: Any, keep: np.ndarray, path_mask: np.ndarray, factor: float) -> Any:
    """Remove the kept edges of ``drop`` and re-route each along the 2-paths ``i - k - j`` of ``w``.

    ``drop``: upper-triangle COO edges ``(i, j, w_ij)``, of which those where ``keep`` is true
    are removed. The removed weight is spread over the common neighbours ``k`` allowed by
    ``path_mask`` (bool per node) in proportion to the series conductances ``w_ik w_kj / (w_ik +
    w_kj)`` and added, times ``factor``, to both edges of each path (``factor = 2`` keeps the
    energy of a linear function whose path node is the edge's midpoint and makes the new
    Laplacian dominate the old one; ``factor = 1`` is the default of
    :class:`HSCPreconditioner`). Edges without such a path are dropped. Returns the symmetric
    increment (scipy CSR) and the weight that found no path.
    """
    import scipy.sparse as sp

    drop_i, drop_j, drop_w = drop.row[keep], drop.col[keep], drop.data[keep]
    n = w.shape[0]
    ne = len(drop_w)
    wk = (w @ sp.diags(path_mask.astype(np.float64))).tocsr()  # edges into allowed path nodes
    wk.sum_duplicates()
    wk.data = np.maximum(wk.data, 0.0)
    wk.eliminate_zeros()
    inv = wk.copy()
    inv.data = 1 / inv.data
    bi, bj = wk[drop_i], wk[drop_j]
    common = bi.multiply(bj).tocsr()  # support: the common neighbours k of each edge
    common.eliminate_zeros()
    common.data[:] = 1.0
    # series conductance 1 / (1 / w_ik + 1 / w_jk) on the common support
    cond = (inv[drop_i] + inv[drop_j]).multiply(common).tocsr()
    cond.eliminate_zeros()
    cond.data = 1 / cond.data
    tot = np.asarray(cond.sum(axis=1)).ravel()
    has = tot > 0
    scale = np.where(has, factor * drop_w / np.where(has, tot, 1), 0.0)
    share = (sp.diags(scale) @ cond).tocsr()  # (edges, n): weight added to (i, k) and (k, j)
    ends = sp.csr_matrix(
        (np.ones(2 * ne), (np.concatenate([drop_i, drop_j]), np.tile(np.arange(ne), 2))),
        shape=(n, ne),
    )
    half = (ends @ share).tocsr()
    inc = (half + half.T).tocsr()
    lost = float(drop_w[~has].sum())
    return inc, lost


def _grounded_graph(matrix: Any) -> tuple[Any, np.ndarray]:
    """Edge weights ``W >= 0`` and ground ``g >= 0`` with ``L(W) + diag(g)`` dominating ``A``.

    Positive off-diagonals (matting, LLE) are removed and added to both diagonals.
    """
    import scipy.sparse as sp

    a = sp.csr_matrix(matrix, dtype=np.float64)
    diag = a.diagonal()
    off = (a - sp.diags(diag)).tocsr()
    off.eliminate_zeros()
    pos = off.multiply(off > 0).tocsr()  # positive off-diagonals -> removed, to diagonals
    wts = (-(off - pos)).tocsr()  # edge weights >= 0
    ground = diag - np.asarray(wts.sum(axis=1)).ravel() + np.asarray(pos.sum(axis=1)).ravel()
    return wts, np.maximum(ground, 0.0)


class HSCPreconditioner(CSRPreconditioner):
    """Hierarchical sparsify-and-compensate preconditioner (Krishnan, Fattal & Szeliski 2013).

    An algebraic reading of the paper for these image systems (CPU, scipy):

    1. The matrix is turned into a grounded graph Laplacian ``L(W) + diag(g)`` with
       non-negative edge weights: positive off-diagonals (matting, LLE) are removed and added
       to both diagonals (the result dominates the original).
    2. Each level splits its nodes geometrically, alternating a checkerboard split of a square
       lattice and the row split of the rotated lattice that follows (the paper's red-black
       scheme), so the coarse nodes form a lattice of twice the spacing every two levels.
    3. *Sparsify*: every edge between two fine (F) nodes is removed and *compensated* along
       the 2-paths through coarse (C) nodes (series-conductance shares, see
       :func:`_compensate`), so ``A_FF`` becomes diagonal.
    4. *Eliminate*: the F nodes are eliminated exactly, ``S = A_CC - A_CF A_FF^{-1} A_FC``.
    5. *Sparsify* ``S``: edges longer than ``keep_radius`` lattice spacings (fill, and the
       non-local LLE couplings) are compensated along 2-paths of the kept edges, then the next
       level starts from ``S``.

    The coarsest level (``<= max_coarse`` unknowns) is factored densely. The preconditioner is
    the exact inverse of the product of these sparsified block factorisations, hence SPD; it
    is applied by one forward and one backward substitution through the levels. The paper's
    exact weighting rules are not reproduced; the scheme above follows its description
    (sparsification of fine-fine connections and of fill, compensation by strengthening nearby
    connections, exact elimination).

    Args:
        matrix: scipy sparse ``(B N, B N)`` SPD matrix.
        shape: ``(B, 1, H, W)``.
        keep_radius: longest kept edge after elimination, in lattice spacings.
        factor: compensation factor (see :func:`_compensate`).
        max_coarse: unknowns of the dense coarsest level.
        coarse_shift: relative diagonal shift of the coarsest matrix (round-off guard).
    """

    def __init__(
        self,
        matrix: Any,
        shape: Sequence[int],
        keep_radius: float = 2.0,
        factor: float = 1.0,
        max_coarse: int = 1500,
        coarse_shift: float = 1e-5,
    ) -> None:
        t0 = time.perf_counter()
        super().__init__(matrix, shape)
        b, _, h, w = self.shape
        wts, ground = _grounded_graph(matrix)
        idx = np.arange(wts.shape[0])
        # every node's lattice position and image
        self._where = (idx % (h * w)) // w, idx % w, idx // (h * w)
        self.keep_radius, self.factor = keep_radius, factor
        self.levels: list[_Elimination] = []
        self.lost: list[float] = []
        nodes = idx  # global ids of the current level's nodes
        level = 0
        while len(nodes) > max_coarse * b and level < 40:
            fine = self._fine_nodes(nodes, level)
            if fine.all() or not fine.any():
                break
            wts, ground, nodes = self._coarsen(wts, ground, nodes, fine, level)
            level += 1
        # coarsest: dense Cholesky of L(W) + diag(g)
        dense = -wts.toarray()
        np.fill_diagonal(dense, np.asarray(wts.sum(axis=1)).ravel() + ground)
        dense[np.diag_indices_from(dense)] *= 1 + coarse_shift
        self._coarse_nodes = nodes
        self._coarse = DenseSPD(torch.from_numpy(dense)[None])
        self.setup_time = time.perf_counter() - t0

    def _fine_nodes(self, nodes: np.ndarray, level: int) -> np.ndarray:
        """The red-black split of a level: a checkerboard, then the rows of the rotated lattice."""
        spacing = 2 ** (level // 2)
        ys, xs = self._where[0][nodes] // spacing, self._where[1][nodes] // spacing
        fine: np.ndarray = (ys + xs) % 2 == 1 if level % 2 == 0 else ys % 2 == 1
        return fine

    def _coarsen(
        self, wts: Any, ground: np.ndarray, nodes: np.ndarray, fine: np.ndarray, level: int
    ) -> tuple[Any, np.ndarray, np.ndarray]:
        """Steps 3-5 of one level: the next level's weights, ground and nodes."""
        import scipy.sparse as sp

        # 3. sparsify F-F edges
        coo = sp.triu(wts, k=1).tocoo()
        ff = fine[coo.row] & fine[coo.col]
        lost = 0.0
        if ff.any():
            inc, lost = _compensate(wts, coo, ff, ~fine, self.factor)
            wts = (wts - _edges(coo, ff, wts.shape) + inc).tocsr()
            wts.eliminate_zeros()
        deg = np.asarray(wts.sum(axis=1)).ravel()
        fi, ci = np.nonzero(fine)[0], np.nonzero(~fine)[0]
        d_f = deg[fi] + ground[fi]
        w_cf = wts[ci][:, fi].tocsr()  # edge weights C-F (A_CF = -w_cf)
        w_cc = wts[ci][:, ci].tocsr()
        # 4. eliminate F: S = A_CC - A_CF D_F^-1 A_FC, as weights and ground
        fill = (w_cf @ sp.diags(1 / d_f) @ w_cf.T).tocsr()
        fill_diag = fill.diagonal()
        d_c = deg[ci] + ground[ci] - fill_diag
        s_w = (w_cc + fill - sp.diags(fill_diag)).tocsr()
        s_w.eliminate_zeros()
        g_c = np.maximum(d_c - np.asarray(s_w.sum(axis=1)).ravel(), 0.0)
        self.levels.append((nodes[fi], nodes[ci], 1 / d_f, w_cf))
        # 5. sparsify long edges of S
        cn = nodes[ci]
        sc = sp.triu(s_w, k=1).tocoo()
        yy, xx, img = self._where
        dy = (yy[cn[sc.row]] - yy[cn[sc.col]]) / (2 ** ((level + 1) / 2))
        dx = (xx[cn[sc.row]] - xx[cn[sc.col]]) / (2 ** ((level + 1) / 2))
        far = (dy * dy + dx * dx > self.keep_radius**2 + 1e-9) | (
            img[cn[sc.row]] != img[cn[sc.col]]
        )
        if far.any():
            near_w = (s_w.copy() - _edges(sc, far, s_w.shape)).tocsr()
            near_w.eliminate_zeros()
            inc, lost2 = _compensate(near_w, sc, far, np.ones(len(ci), dtype=bool), self.factor)
            s_w = (near_w + inc).tocsr()
            lost += lost2
        self.lost.append(lost)
        return s_w, g_c, cn

    def apply(self, r: torch.Tensor) -> torch.Tensor:
        """``M^{-1} r`` for ``r`` ``(B, 1, H, W)`` (CPU; computed in float64)."""
        self._check(r)
        v = r.detach().cpu().double().numpy().reshape(-1).copy()
        ys = []
        for f, c, df_inv, w_cf in self.levels:
            y = df_inv * v[f]
            v[c] += w_cf @ y  # r_C - A_CF y_F with A_CF = -w_cf
            ys.append(y)
        cn = self._coarse_nodes
        rc = torch.from_numpy(v[cn]).view(1, -1, 1)
        v[cn] = self._coarse.solve(rc).numpy().ravel()
        for (f, c, df_inv, w_cf), y in zip(reversed(self.levels), reversed(ys), strict=True):
            v[f] = y + df_inv * (w_cf.T @ v[c])  # y_F - D_F^-1 A_FC x_C
        return torch.from_numpy(v).to(dtype=r.dtype, device=r.device).view(r.shape)

    __call__ = apply
