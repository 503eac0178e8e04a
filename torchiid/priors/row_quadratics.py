"""Quadratic terms over explicit rows: pixel pairs, sparse constraint rows, single pixels.

The non-stencil shading terms: :class:`PairQuadratic` (a list of pixel pairs, the global
prior's representatives), :class:`ConstraintQuadratic` (general sparse rows, the LLE term
``S_c``) and :class:`DiagonalQuadratic` (an anchor or a pin on individual pixels), each a
:class:`~torchiid.priors.quadratic_term.QuadraticTerm`.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property

import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.pairs import PairSet
from torchiid.priors.quadratic_term import QuadraticTerm, sparse_gram

__all__ = ["PairQuadratic", "ConstraintQuadratic", "DiagonalQuadratic"]


class PairQuadratic(QuadraticTerm):
    """``sum_p w_p (x_{i_p} - x_{j_p} - c_p)^2`` over a :class:`PairSet`.

    Args:
        pairs: the pair list.
        weights: ``(B, P)`` non-negative weights.
        target: optional ``(B, P)`` target differences.
    """

    def __init__(
        self, pairs: PairSet, weights: torch.Tensor, target: torch.Tensor | None = None
    ) -> None:
        if weights.dim() != 2 or weights.shape[1] != pairs.num_pairs:
            raise ShapeError(f"expected weights (B, {pairs.num_pairs}), got {tuple(weights.shape)}")
        if target is not None and target.shape != weights.shape:
            raise ShapeError(
                f"target {tuple(target.shape)} must match weights {tuple(weights.shape)}"
            )
        self.pairs = pairs
        self.weights = weights
        self.target = target
        self.shape = (weights.shape[0], 1, pairs.height, pairs.width)
        self.dtype = weights.dtype
        self.device = weights.device

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``M^T W M x`` with gather/scatter."""
        self._check(x)
        return self.pairs.laplacian_matvec(self.weights, x)

    def diagonal(self) -> torch.Tensor:
        """``diag(A)``."""
        return self.pairs.laplacian_diagonal(self.weights)

    def rhs(self) -> torch.Tensor:
        """``M^T W c``."""
        if self.target is None:
            return super().rhs()
        return self.pairs.adjoint((self.weights * self.target).unsqueeze(1))

    def to_sparse(self) -> torch.Tensor:
        """``D^T D`` from :meth:`PairSet.difference_matrix`."""
        return sparse_gram(self.pairs.difference_matrix(self.weights))


class ConstraintQuadratic(QuadraticTerm):
    """``sum_r w_r ((M x)_r - c_r)^2`` for general sparse constraint rows ``M``.

    Args:
        matrix: sparse ``(B R, B H W)`` block-diagonal rows (see
            :func:`~torchiid.priors.pairs.constraint_matrix`).
        shape: the unknown's shape ``(B, 1, H, W)``.
        weights: optional ``(B R,)`` non-negative row weights (default 1).
        target: optional ``(B R,)`` row targets ``c`` (default 0).
    """

    def __init__(
        self,
        matrix: torch.Tensor,
        shape: Sequence[int],
        weights: torch.Tensor | None = None,
        target: torch.Tensor | None = None,
    ) -> None:
        shape = tuple(int(s) for s in shape)
        n = shape[0] * shape[2] * shape[3]
        if len(shape) != 4 or shape[1] != 1 or matrix.shape[1] != n:
            raise ShapeError(
                f"constraint matrix {tuple(matrix.shape)} does not fit unknowns of shape {shape}"
            )
        r = matrix.shape[0]
        for name, v in (("weights", weights), ("target", target)):
            if v is not None and tuple(v.shape) != (r,):
                raise ShapeError(f"expected {name} of shape ({r},), got {tuple(v.shape)}")
        self.matrix = matrix.coalesce()
        self.matrix_t = self.matrix.t().coalesce()
        self.row_weights = (
            torch.ones(r, dtype=matrix.dtype, device=matrix.device) if weights is None else weights
        )
        self.target = target
        self.shape = shape
        self.dtype = matrix.dtype
        self.device = matrix.device

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``M^T W M x``: two sparse products, or on the CPU a gather and two index-adds."""
        self._check(x)
        if self.device.type == "cpu":
            return self.add_matvec(x, torch.zeros_like(x))
        mx = torch.sparse.mm(self.matrix, x.reshape(-1, 1))
        out: torch.Tensor = torch.sparse.mm(self.matrix_t, self.row_weights.view(-1, 1) * mx)
        return out.view(self.shape)

    def add_matvec(self, x: torch.Tensor, out: torch.Tensor, alpha: float = 1.0) -> torch.Tensor:
        """``out += alpha · M^T W M x`` (in place, returns ``out``).

        On the CPU the rows are few (one per patch) against ``H·W`` unknowns, so the product
        gathers the entries it needs and index-adds the rows' contributions into ``out``,
        without the two ``torch.sparse.mm`` calls and the pass that adds their ``(H·W)``
        result. On other devices the sparse products (``index_add_`` there sums with atomics,
        in no fixed order).
        """
        self._check(x)
        if self.device.type != "cpu":
            return out.add_(self.matvec(x), alpha=alpha)
        rows, cols, vals = self._entries
        mx = x.new_zeros(self.matrix.shape[0]).index_add_(0, rows, vals * x.reshape(-1)[cols])
        scaled = (self.row_weights * mx).mul_(alpha)
        out.view(-1).index_add_(0, cols, scaled[rows] * vals)
        return out

    @cached_property
    def _entries(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        idx = self.matrix.indices()
        return idx[0].contiguous(), idx[1].contiguous(), self.matrix.values()

    def diagonal(self) -> torch.Tensor:
        """``diag(A)_c = sum_r w_r M_rc^2``."""
        idx, val = self.matrix.indices(), self.matrix.values()
        d = torch.zeros(self.matrix.shape[1], dtype=self.dtype, device=self.device)
        d.index_add_(0, idx[1], self.row_weights[idx[0]] * val * val)
        return d.view(self.shape)

    def rhs(self) -> torch.Tensor:
        """``M^T W c``."""
        if self.target is None:
            return super().rhs()
        wc = (self.row_weights * self.target).view(-1, 1)
        out: torch.Tensor = torch.sparse.mm(self.matrix_t, wc)
        return out.view(self.shape)

    def to_sparse(self) -> torch.Tensor:
        """``M^T W M`` assembled."""
        idx, val = self.matrix.indices(), self.matrix.values()
        sw = self.row_weights.clamp_min(0).sqrt()
        d = torch.sparse_coo_tensor(
            idx, val * sw[idx[0]], self.matrix.shape, check_invariants=False
        )
        return sparse_gram(d.coalesce())


class DiagonalQuadratic(QuadraticTerm):
    """``sum_i a_i (x_i - t_i)^2``: an anchor (or a pin) on individual pixels.

    Args:
        weights: ``(B, 1, H, W)`` non-negative ``a``.
        target: ``(B, 1, H, W)`` targets ``t`` (default 0).
    """

    def __init__(self, weights: torch.Tensor, target: torch.Tensor | None = None) -> None:
        if weights.dim() != 4 or weights.shape[1] != 1:
            raise ShapeError(f"expected weights (B, 1, H, W), got {tuple(weights.shape)}")
        self.weights = weights
        self.target = target
        b, _, h, w = weights.shape
        self.shape = (b, 1, h, w)
        self.dtype = weights.dtype
        self.device = weights.device

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``diag(a) x``."""
        self._check(x)
        return self.weights * x

    def diagonal(self) -> torch.Tensor:
        """``a``."""
        return self.weights

    def rhs(self) -> torch.Tensor:
        """``a t``."""
        return super().rhs() if self.target is None else self.weights * self.target

    def to_sparse(self) -> torch.Tensor:
        """``diag(a)``."""
        n = self.weights.numel()
        i = torch.arange(n, device=self.device)
        return torch.sparse_coo_tensor(
            torch.stack([i, i]), self.weights.reshape(-1), (n, n), check_invariants=False
        )
