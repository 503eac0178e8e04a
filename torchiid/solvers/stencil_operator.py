"""The shading system as a stencil operator: what the multigrid hierarchy is built from.

The shading system ``A = D_m Psi D_m + diag(extra)`` (Eq. 1 plus the gauge anchor and the pinning
of masked-out pixels, see :func:`~torchiid.stages.shading.anchored_system`) is a 5x5-stencil graph
Laplacian, a handful of non-local rows (the LLE term ``S_c``) and a diagonal.
:class:`StencilOperator` holds it in that form: per-offset coefficient planes, the diagonal and
the non-local rows in factored form ``M^T diag(w) M``, so that every product is a shifted
elementwise product or a tiny sparse product and no sparse matrix of the image is assembled.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.quadratic import (
    ConstraintQuadratic,
    DiagonalQuadratic,
    PairQuadratic,
    QuadraticTerm,
    StencilQuadratic,
    SumQuadratic,
)
from torchiid.priors.stencil import shift_slices

__all__ = ["StencilOperator", "Factor", "is_half_offset"]

#: non-local rows ``(M, w)``: a sparse COO ``(B R, B H W)`` matrix and its ``(B R,)`` weights
Factor = tuple[torch.Tensor, torch.Tensor]

#: one offset's product: the slices of ``i`` and ``j = i + o`` and the coefficients at ``i``
_ShiftOp = tuple[slice, slice, slice, slice, torch.Tensor]


def is_half_offset(o: tuple[int, int]) -> bool:
    """Whether ``o = (dy, dx)`` lists its pair once: ``dy > 0`` or ``dy == 0 < dx``."""
    return o[0] > 0 or (o[0] == 0 and o[1] > 0)


class StencilOperator:
    """A symmetric operator on ``(B, C, H, W)`` images: stencil + diagonal + factored rows.

    ``A = sum_k (a_k shift_k + shift_k^T a_k) + diag(d) + sum_f M_f^T diag(w_f) M_f``: for each
    half offset ``o_k = (dy, dx)`` (``dy > 0`` or ``dy == 0 < dx``) ``a[:, k, y, x]`` is the matrix
    entry ``A[(y, x), (y + dy, x + dx)]`` (0 where the partner is outside), ``d`` the diagonal
    of the stencil part, and each factor ``(M, w)`` a block-diagonal sparse ``(B R, B H W)`` row
    matrix with row weights (the non-local ``S_c`` rows). The channel dimension ``C`` holds
    independent vectors (probes); coefficients broadcast over it.

    Args:
        offsets: the ``K`` half offsets.
        a: ``(B, K, H, W)`` off-diagonal entries.
        d: ``(B, 1, H, W)`` diagonal of the stencil part.
        factors: ``(M, w)`` pairs: sparse COO ``(B R, B H W)`` and ``(B R,)``.
    """

    def __init__(
        self,
        offsets: Sequence[tuple[int, int]],
        a: torch.Tensor,
        d: torch.Tensor,
        factors: Sequence[Factor] = (),
    ) -> None:
        self.offsets = [(int(dy), int(dx)) for dy, dx in offsets]
        if any(not is_half_offset(o) for o in self.offsets):
            raise ShapeError(f"offsets must be half offsets, got {self.offsets}")
        if (
            a.dim() != 4
            or a.shape[1] != len(self.offsets)
            or d.shape != (a.shape[0], 1, *a.shape[2:])
        ):
            raise ShapeError(f"inconsistent stencil shapes a={tuple(a.shape)} d={tuple(d.shape)}")
        self.a = a.contiguous()
        self.d = d.contiguous()
        self.factors = [(m.coalesce(), w) for m, w in factors]
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            # M x as a CSR product, M^T y as a scatter (both 10x faster than COO products)
            self._csr = [
                (
                    m.to_sparse_csr(),
                    m.indices()[0],
                    m.indices()[1],
                    m.values().view(-1, 1),
                    w.view(-1, 1),
                )
                for m, w in self.factors
            ]
        self.batch, _, self.height, self.width = d.shape
        # slices and coefficient views of every offset, computed once
        self._ops: list[_ShiftOp] = []
        for k, (dy, dx) in enumerate(self.offsets):
            yi, xi, yj, xj = shift_slices(dy, dx, self.height, self.width)
            if yi.stop > yi.start and xi.stop > xi.start:
                self._ops.append((yi, xi, yj, xj, self.a[:, k : k + 1, yi, xi]))

    # -- basic properties -----------------------------------------------------------------
    @property
    def radius(self) -> int:
        """Largest ``max(|dy|, |dx|)`` of the stencil (0 if diagonal)."""
        return max((max(abs(dy), abs(dx)) for dy, dx in self.offsets), default=0)

    @property
    def dtype(self) -> torch.dtype:
        """Coefficient dtype."""
        return self.d.dtype

    @property
    def device(self) -> torch.device:
        """Coefficient device."""
        return self.d.device

    @property
    def numel(self) -> int:
        """Unknowns per image ``H W``."""
        return self.height * self.width

    def to(
        self, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> StencilOperator:
        """A copy with coefficients converted."""
        return StencilOperator(
            self.offsets,
            self.a.to(dtype=dtype, device=device),
            self.d.to(dtype=dtype, device=device),
            [
                (m.to(dtype=dtype, device=device), w.to(dtype=dtype, device=device))
                for m, w in self.factors
            ],
        )

    def local(self) -> StencilOperator:
        """The stencil and diagonal only (factored rows dropped)."""
        return StencilOperator(self.offsets, self.a, self.d)

    # -- products ---------------------------------------------------------------------------
    def stencil_matvec(self, x: torch.Tensor) -> torch.Tensor:
        """The stencil and diagonal part times ``x`` ``(B, C, H, W)``."""
        y = self.d * x
        for yi, xi, yj, xj, ak in self._ops:
            y[:, :, yi, xi].addcmul_(ak, x[:, :, yj, xj])
            y[:, :, yj, xj].addcmul_(ak, x[:, :, yi, xi])
        return y

    def factor_matvec(self, x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Add the factored rows' product ``sum_f M_f^T w_f M_f x`` to ``out`` (in place)."""
        if not self.factors:
            return out
        b, c, h, w = x.shape
        # (B H W, C) with standard strides (a permuted view is 100x slower in the CSR kernel)
        xc = x.reshape(-1, 1) if c == 1 else x.permute(0, 2, 3, 1).reshape(b * h * w, c)
        xc = xc.contiguous() if c == 1 else xc.clone(memory_format=torch.contiguous_format)
        for m, rows, cols, vals, wr in self._csr:
            t = wr * (m @ xc)
            acc = torch.zeros(b * h * w, c, dtype=out.dtype, device=out.device)
            acc.index_add_(0, cols, vals * t[rows])
            out += acc.view(b, h, w, c).permute(0, 3, 1, 2)
        return out

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``A x`` for ``x`` ``(B, C, H, W)``."""
        if x.shape[0] != self.batch or x.shape[2:] != (self.height, self.width):
            raise ShapeError(
                f"expected x (B={self.batch}, C, {self.height}, {self.width}), got {tuple(x.shape)}"
            )
        return self.factor_matvec(x, self.stencil_matvec(x))

    __call__ = matvec

    def diagonal(self) -> torch.Tensor:
        """``diag(A)`` ``(B, 1, H, W)`` including the factored rows."""
        d = self.d.clone()
        n = self.batch * self.numel
        for m, wr in self.factors:
            idx, val = m.indices(), m.values()
            extra = torch.zeros(n, dtype=d.dtype, device=d.device)
            extra.index_add_(0, idx[1], wr[idx[0]] * val * val)
            d += extra.view_as(d)
        return d

    def to_dense(self) -> torch.Tensor:
        """``(B, N, N)`` dense matrix of every image (small grids only)."""
        b, h, w = self.batch, self.height, self.width
        n = h * w
        dense = torch.zeros(b, n, n, dtype=self.dtype, device=self.device)
        ar = torch.arange(n, device=self.device)
        dense[:, ar, ar] = self.d.reshape(b, n)
        flat = ar.view(h, w)
        for k, (dy, dx) in enumerate(self.offsets):
            yi, xi, yj, xj = shift_slices(dy, dx, h, w)
            i = flat[yi, xi].reshape(-1)
            j = flat[yj, xj].reshape(-1)
            v = self.a[:, k, yi, xi].reshape(b, -1)
            dense[:, i, j] += v
            dense[:, j, i] += v
        for m, wr in self.factors:
            md = m.to_dense()
            r = md.shape[0] // b
            for bb in range(b):
                blk = md[bb * r : (bb + 1) * r, bb * n : (bb + 1) * n]
                dense[bb] += blk.T @ (wr[bb * r : (bb + 1) * r].view(-1, 1) * blk)
        return dense

    def to_scipy(self) -> Any:
        """The block-diagonal ``(B N, B N)`` matrix as scipy CSR (float64), on the CPU."""
        import scipy.sparse as sp

        b, h, w = self.batch, self.height, self.width
        n = b * h * w
        a = self.a.detach().to("cpu", torch.float64).numpy()
        offs, data = [0], [self.d.detach().to("cpu", torch.float64).numpy().reshape(-1)]
        for k, (dy, dx) in enumerate(self.offsets):
            f = dy * w + dx
            ak = a[:, k].reshape(-1)  # entry (i, i + f) at row i; 0 where it leaves the image
            up = np.zeros(n)
            up[f:] = ak[: n - f]  # dia convention: data[j] = A[j - f, j]
            lo = np.zeros(n)
            lo[: n - f] = ak[: n - f]  # A[j + f, j] = A[j, j + f]
            offs += [f, -f]
            data += [up, lo]
        mat = sp.dia_matrix((np.stack(data), np.array(offs)), shape=(n, n)).tocsr()
        mat.eliminate_zeros()
        for m, wr in self.factors:
            mm = m.detach().to("cpu", torch.float64).coalesce()
            i, j = mm.indices().numpy()
            ms = sp.csr_matrix((mm.values().numpy(), (i, j)), shape=tuple(mm.shape))
            wd = sp.diags(wr.detach().to("cpu", torch.float64).numpy())
            mat = mat + (ms.T @ wd @ ms).tocsr()
        return mat.tocsr()

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def from_quadratic(
        cls,
        total: QuadraticTerm,
        extra_diag: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        dtype: torch.dtype | None = None,
    ) -> StencilOperator:
        """``D_m total D_m + diag(extra_diag)`` from a :class:`SumQuadratic` (or one term).

        Stencil terms become the stencil (offsets merged), constraint and pair terms factored
        rows, diagonal terms the diagonal. ``mask`` (0/1) restricts every term to the masked
        pixels as ``solve_shading``'s product does.

        Raises:
            ShapeError: a term of another type (it has no stencil or factored form).
        """
        terms = total.terms if isinstance(total, SumQuadratic) else [(1.0, total)]
        b, _, h, w = total.shape
        dt = dtype or total.dtype
        dev = total.device
        offsets = _merged_offsets(terms)
        pos = {o: k for k, o in enumerate(offsets)}
        a = torch.zeros(b, len(offsets), h, w, dtype=dt, device=dev)
        d = torch.zeros(b, 1, h, w, dtype=dt, device=dev)
        factors: list[Factor] = []
        for lam, t in terms:
            if isinstance(t, StencilQuadratic):
                wt = t.weights.to(dt) * lam
                for k, o in enumerate(t.stencil.offsets):
                    a[:, pos[o]] -= wt[:, k]
                d += t.stencil.laplacian_diagonal(wt)
            elif isinstance(t, ConstraintQuadratic):
                factors.append((t.matrix.to(dt), t.row_weights.to(dt) * lam))
            elif isinstance(t, PairQuadratic):
                mat = t.pairs.difference_matrix(t.weights.to(dt))  # rows sqrt(w) (e_i - e_j)
                factors.append((mat, torch.full((mat.shape[0],), lam, dtype=dt, device=dev)))
            elif isinstance(t, DiagonalQuadratic):
                d += lam * t.weights.to(dt)
            else:
                raise ShapeError(
                    f"{type(t).__name__} has no stencil or factored form; "
                    "use AMGPreconditioner on its assembled matrix"
                )
        if mask is not None:
            m = mask.to(device=dev, dtype=dt).reshape(b, 1, h, w)
            d, factors = _restrict_to_mask(offsets, a, d, factors, m)
        if extra_diag is not None:
            d = d + extra_diag.to(device=dev, dtype=dt).reshape(b, 1, h, w)
        return cls(offsets, a, d, factors)


def _merged_offsets(terms: Sequence[tuple[float, QuadraticTerm]]) -> list[tuple[int, int]]:
    """The sorted union of the stencil terms' offsets (each a half offset)."""
    offsets: list[tuple[int, int]] = []
    for _, t in terms:
        if isinstance(t, StencilQuadratic):
            for o in t.stencil.offsets:
                if not is_half_offset(o):
                    raise ShapeError(f"stencil offset {o} is not a half offset")
                if o not in offsets:
                    offsets.append(o)
    offsets.sort()
    return offsets


def _restrict_to_mask(
    offsets: Sequence[tuple[int, int]],
    a: torch.Tensor,
    d: torch.Tensor,
    factors: list[Factor],
    m: torch.Tensor,
) -> tuple[torch.Tensor, list[Factor]]:
    """``D_m A D_m`` for a 0/1 mask ``m`` ``(B, 1, H, W)``: ``a`` in place, new ``d`` and rows."""
    h, w = a.shape[2:]
    for k, (dy, dx) in enumerate(offsets):
        yi, xi, yj, xj = shift_slices(dy, dx, h, w)
        a[:, k, yi, xi] *= m[:, 0, yi, xi] * m[:, 0, yj, xj]
    mf = m.reshape(-1)
    masked = []
    for mm, wr in factors:  # M D_m: drop the columns of pixels outside
        mm = mm.coalesce()
        idx = mm.indices()
        vals = mm.values() * mf[idx[1]]
        masked.append((torch.sparse_coo_tensor(idx, vals, mm.shape, check_invariants=False), wr))
    return d * m, masked
