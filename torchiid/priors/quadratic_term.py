"""Sparse quadratic energies ``E(x) = x^T A x - 2 b^T x + const`` over a one-channel image.

Every shading prior of the paper (Eq. 1-5) is a sum of squared, weighted linear residuals
``E(x) = sum_r w_r ((M x)_r - c_r)^2`` with a difference or constraint operator ``M``, so
``A = M^T W M`` is symmetric positive semi-definite by construction and ``b = M^T W c``.
A :class:`QuadraticTerm` offers what a conjugate-gradient solver needs -- :meth:`matvec`,
:meth:`diagonal` (Jacobi), :meth:`rhs` -- plus :meth:`to_sparse`, the assembled torch sparse
matrix ``A`` that serves as the canonical, tested reference of the fast products.

The unknown ``x`` is ``(B, 1, H, W)``; a batch is the block-diagonal system on ``B * H * W``
unknowns, flat index ``b * H * W + y * W + x``.
"""

from __future__ import annotations

import warnings

import torch

from torchiid.core.exceptions import ShapeError

__all__ = ["QuadraticTerm", "sparse_gram"]


def sparse_gram(d: torch.Tensor) -> torch.Tensor:
    """``D^T D`` of a sparse COO matrix ``D``, as a coalesced sparse COO matrix."""
    with warnings.catch_warnings():
        # torch routes sparse @ sparse through CSR and warns that CSR is "beta"
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        gram: torch.Tensor = torch.sparse.mm(d.t().coalesce(), d).coalesce()
        return gram


class QuadraticTerm:
    """Base class: a PSD quadratic ``x^T A x - 2 b^T x`` on ``(B, 1, H, W)`` images.

    Subclasses set ``shape`` (the unknown's shape ``(B, 1, H, W)``) and implement
    :meth:`matvec`, :meth:`diagonal` and :meth:`to_sparse`; :meth:`rhs` defaults to zero.
    """

    shape: tuple[int, int, int, int]
    dtype: torch.dtype
    device: torch.device

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``A x`` for ``x`` of shape ``(B, 1, H, W)``."""
        raise NotImplementedError

    def diagonal(self) -> torch.Tensor:
        """``diag(A)`` as ``(B, 1, H, W)``."""
        raise NotImplementedError

    def rhs(self) -> torch.Tensor:
        """The linear part ``b`` (``(B, 1, H, W)``); the minimiser solves ``A x = b``."""
        return torch.zeros(self.shape, dtype=self.dtype, device=self.device)

    def to_sparse(self) -> torch.Tensor:
        """``A`` assembled as a sparse COO ``(B H W, B H W)`` matrix (the reference)."""
        raise NotImplementedError

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        """``x^T A x - 2 b^T x`` per image, ``(B,)`` (the energy up to a constant)."""
        return ((self.matvec(x) - 2 * self.rhs()) * x).flatten(1).sum(1)

    def _check(self, x: torch.Tensor) -> None:
        if tuple(x.shape) != tuple(self.shape):
            raise ShapeError(f"expected x of shape {tuple(self.shape)}, got {tuple(x.shape)}")
