"""Arbitrary pair lists and constraint rows as batched sparse operators.

:class:`~torchiid.priors.stencil.Stencil` covers fixed-offset neighbourhoods (3x3, 11x11).
This module covers what a stencil cannot express:

* :class:`PairSet` -- an arbitrary list of pixel pairs ``(i, j)`` per image (e.g. all pairs of
  a set of representative pixels, or a stencil flattened to a list). Its difference operator is
  ``(M x)_p = x_{i_p} - x_{j_p}``.
* :func:`constraint_matrix` -- general linear constraint rows ``r(x) = sum_c v_{rc} x_c`` (e.g.
  the LLE rows ``s_b - sum_a w_ab s_a`` of Eq. 2), one image after another, as a block-diagonal
  torch sparse matrix.

Pixels are flat indices ``y * W + x`` within one image; a batch of ``B`` images is the
block-diagonal system on ``B * H * W`` unknowns. Everything is built with vectorised torch ops on
the device and dtype of the inputs.
"""

from __future__ import annotations

import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.stencil import Stencil

__all__ = ["PairSet", "constraint_matrix", "block_diagonal_index"]


def block_diagonal_index(index: torch.Tensor, block: int) -> torch.Tensor:
    """Shift per-image indices ``(B, P)`` into a block-diagonal numbering ``(B * P,)``.

    Image ``b``'s index ``t`` becomes ``b * block + t``.
    """
    b = index.shape[0]
    offs = torch.arange(b, device=index.device, dtype=index.dtype).view(-1, 1) * block
    return (index + offs).reshape(-1)


class PairSet:
    """A list of pixel pairs on an ``H x W`` grid, shared by the batch or given per image.

    Args:
        i: first pixel's flat index, ``(P,)`` (same pairs for every image) or ``(B, P)``.
        j: second pixel's flat index, same shape as ``i``.
        height: image height ``H``.
        width: image width ``W``.

    Raises:
        ShapeError: ``i`` and ``j`` differ in shape or are not 1-D/2-D integer tensors.
        ParameterError: the set is empty or an index lies outside ``[0, H * W)``.

    Shape:
        Pair values are ``(B, C, P)``; pair weights ``(B, P)``.
    """

    def __init__(self, i: torch.Tensor, j: torch.Tensor, height: int, width: int) -> None:
        if not isinstance(i, torch.Tensor) or not isinstance(j, torch.Tensor):
            raise ShapeError("pair indices must be torch tensors")
        if i.shape != j.shape or i.dim() not in (1, 2):
            raise ShapeError(
                f"expected pair indices i, j of equal shape (P,) or (B, P), got "
                f"{tuple(i.shape)} and {tuple(j.shape)}"
            )
        if i.is_floating_point() or j.is_floating_point():
            raise ShapeError(f"pair indices must be integer tensors, got {i.dtype}")
        if i.shape[-1] == 0:
            raise ParameterError("empty pair set: at least one pair (i, j) is needed")
        n = int(height) * int(width)
        lo = int(torch.minimum(i.min(), j.min()))
        hi = int(torch.maximum(i.max(), j.max()))
        if lo < 0 or hi >= n:
            raise ParameterError(
                f"pair indices must lie in [0, {n}) for a {height}x{width} image, "
                f"got range [{lo}, {hi}]"
            )
        self.i = i.long()
        self.j = j.long()
        self.height = int(height)
        self.width = int(width)

    @classmethod
    def from_stencil(cls, stencil: Stencil) -> PairSet:
        """All valid pairs of a stencil, in the order of :meth:`Stencil.pair_index`."""
        _, i, j = stencil.pair_index()
        return cls(i, j, stencil.height, stencil.width)

    @classmethod
    def all_pairs(cls, index: torch.Tensor, height: int, width: int) -> PairSet:
        """Every unordered pair of a point set (each once), e.g. representative pixels.

        Args:
            index: flat pixel indices ``(Q,)`` or ``(B, Q)`` (pad with repeats and give the
                padded pairs weight 0 when images have different counts).
            height: image height.
            width: image width.
        """
        q = index.shape[-1]
        if q < 2:
            raise ParameterError(f"all_pairs needs at least 2 points, got {q}")
        a, b = torch.triu_indices(q, q, offset=1, device=index.device)
        return cls(index[..., a], index[..., b], height, width)

    @property
    def num_pairs(self) -> int:
        """``P``, the number of pairs per image."""
        return int(self.i.shape[-1])

    def _idx(self, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        i, j = self.i, self.j
        if i.dim() == 1:
            i = i.expand(batch, -1)
            j = j.expand(batch, -1)
        elif i.shape[0] != batch:
            raise ShapeError(
                f"pair set holds pairs for {i.shape[0]} images but the input has batch {batch}"
            )
        return i, j

    def _check_x(self, x: torch.Tensor) -> None:
        if x.dim() != 4 or x.shape[-2:] != (self.height, self.width):
            raise ShapeError(
                f"expected x of shape (B, C, {self.height}, {self.width}), got {tuple(x.shape)}"
            )

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Pair differences ``M x``: ``(B, C, H, W) -> (B, C, P)``."""
        self._check_x(x)
        b, c = x.shape[:2]
        i, j = self._idx(b)
        flat = x.reshape(b, c, -1)
        gi = torch.gather(flat, 2, i.unsqueeze(1).expand(b, c, -1))
        gj = torch.gather(flat, 2, j.unsqueeze(1).expand(b, c, -1))
        return gi - gj

    def adjoint(self, d: torch.Tensor) -> torch.Tensor:
        """``M^T d``: scatter pair values ``(B, C, P)`` back to ``(B, C, H, W)``."""
        if d.dim() != 3 or d.shape[-1] != self.num_pairs:
            raise ShapeError(f"expected pair values (B, C, {self.num_pairs}), got {tuple(d.shape)}")
        b, c = d.shape[:2]
        i, j = self._idx(b)
        out = d.new_zeros(b, c, self.height * self.width)
        out.scatter_add_(2, i.unsqueeze(1).expand(b, c, -1), d)
        out.scatter_add_(2, j.unsqueeze(1).expand(b, c, -1), -d)
        return out.view(b, c, self.height, self.width)

    def laplacian_matvec(self, weights: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``M^T diag(w) M x`` for weights ``(B, P)`` and ``x`` ``(B, C, H, W)``."""
        return self.adjoint(weights.unsqueeze(1) * self.apply(x))

    def laplacian_diagonal(self, weights: torch.Tensor) -> torch.Tensor:
        """Diagonal of ``M^T diag(w) M``: ``(B, P) -> (B, 1, H, W)``."""
        b = weights.shape[0]
        i, j = self._idx(b)
        out = weights.new_zeros(b, self.height * self.width)
        out.scatter_add_(1, i, weights)
        out.scatter_add_(1, j, weights)
        return out.view(b, 1, self.height, self.width)

    def difference_matrix(self, weights: torch.Tensor) -> torch.Tensor:
        """The weighted difference operator as a block-diagonal sparse COO matrix.

        Args:
            weights: ``(B, P)`` non-negative pair weights; rows are scaled by ``sqrt(w)`` so
                that ``D^T D = M^T diag(w) M``.

        Returns:
            Sparse ``(B * P, B * H * W)`` matrix.
        """
        b, p = weights.shape
        i, j = self._idx(b)
        n = self.height * self.width
        sw = weights.clamp_min(0).sqrt().reshape(-1)
        rows = torch.arange(b * p, device=weights.device)
        cols = torch.cat([block_diagonal_index(i, n), block_diagonal_index(j, n)])
        idx = torch.stack([torch.cat([rows, rows]), cols])
        return torch.sparse_coo_tensor(
            idx, torch.cat([sw, -sw]), (b * p, b * n), check_invariants=False
        ).coalesce()


def constraint_matrix(
    rows: torch.Tensor,
    cols: torch.Tensor,
    values: torch.Tensor,
    num_rows: int,
    height: int,
    width: int,
) -> torch.Tensor:
    """Linear constraint rows of a batch as a block-diagonal sparse COO matrix.

    Entry ``(b, r, c)`` with value ``v`` means row ``r`` of image ``b`` contains ``v * x_c``.

    Args:
        rows: ``(B, E)`` row index of every entry, in ``[0, num_rows)``.
        cols: ``(B, E)`` flat pixel index of every entry, in ``[0, H * W)``.
        values: ``(B, E)`` floating entry values (0 for padding).
        num_rows: ``R``, rows per image.
        height: image height.
        width: image width.

    Returns:
        Sparse ``(B * R, B * H * W)`` matrix (duplicates summed).

    Raises:
        ShapeError: mismatched shapes.
        ParameterError: no rows, or an index out of range.
    """
    if not (rows.shape == cols.shape == values.shape) or rows.dim() != 2:
        raise ShapeError(
            f"expected rows, cols, values of one shape (B, E), got {tuple(rows.shape)}, "
            f"{tuple(cols.shape)}, {tuple(values.shape)}"
        )
    n = int(height) * int(width)
    if num_rows < 1 or rows.shape[1] == 0:
        raise ParameterError("empty constraint set: at least one row with one entry is needed")
    if int(rows.min()) < 0 or int(rows.max()) >= num_rows:
        raise ParameterError(f"constraint row indices must lie in [0, {num_rows})")
    if int(cols.min()) < 0 or int(cols.max()) >= n:
        raise ParameterError(f"constraint column indices must lie in [0, {n})")
    b = rows.shape[0]
    idx = torch.stack(
        [block_diagonal_index(rows.long(), num_rows), block_diagonal_index(cols.long(), n)]
    )
    return torch.sparse_coo_tensor(
        idx, values.reshape(-1), (b * num_rows, b * n), check_invariants=False
    ).coalesce()
