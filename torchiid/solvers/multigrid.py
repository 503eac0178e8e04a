"""Multigrid preconditioners for the shading solve.

The shading system (a 5x5-stencil graph Laplacian with near-binary, strongly discontinuous
Retinex weights, a few small positive off-diagonals from the matting Laplacian and a handful of
non-local LLE rows; :mod:`torchiid.solvers.stencil_operator`) takes Jacobi-preconditioned CG
hundreds to thousands of iterations. A multigrid V-cycle brings that to about ten; each
preconditioner here is a fixed, symmetric positive definite linear operator, so plain
(non-flexible) PCG stays valid:

* :class:`GalerkinMultigrid` -- torch only (CPU or CUDA, batched): smoothed aggregation with
  exact Galerkin coarse operators kept as stencils (:mod:`torchiid.solvers.hierarchy`),
  Chebyshev smoothing (:mod:`torchiid.solvers.smoothers`) and a dense float64 solve on the
  coarsest grid. No sparse matrix of the image is ever assembled.
* :class:`~torchiid.solvers.amg.AMGPreconditioner` -- pyamg smoothed aggregation on the
  assembled scipy CSR matrix (CPU only).
* :class:`~torchiid.solvers.hsc.HSCPreconditioner` -- hierarchical sparsify-and-compensate
  after Krishnan, Fattal & Szeliski (SIGGRAPH 2013).

:func:`~torchiid.solvers.pcg.pcg_callable` runs PCG with any of them and records the residual
history. The names of those modules are importable from here too.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import torch

from torchiid.core.exceptions import ShapeError
from torchiid.solvers.amg import AMGPreconditioner
from torchiid.solvers.dense import DenseSPD
from torchiid.solvers.hierarchy import Level, Transfer, aggregation, galerkin
from torchiid.solvers.hsc import HSCPreconditioner
from torchiid.solvers.pcg import PCGHistory, pcg_callable
from torchiid.solvers.smoothers import chebyshev, lanczos_lmax
from torchiid.solvers.stencil_operator import StencilOperator
from torchiid.solvers.system import System, SystemPreconditioner, assemble_csr

if TYPE_CHECKING:
    from typing_extensions import Self

__all__ = [
    "StencilOperator",
    "GalerkinMultigrid",
    "AMGPreconditioner",
    "HSCPreconditioner",
    "assemble_csr",
    "PCGHistory",
    "pcg_callable",
]


class GalerkinMultigrid(SystemPreconditioner):
    """Torch-only smoothed-aggregation multigrid V-cycle, an SPD preconditioner.

    Hierarchy (:mod:`torchiid.solvers.hierarchy`): ``block x block`` aggregates, a prolongation
    smoothed once by damped Jacobi on the level's local stencil (``omega = prolong_omega /
    lambda_max(D_l^{-1} A_l)``), exact Galerkin coarse operators ``A_c = P^T A P`` with the
    non-local rows kept factored. Coarsening stops when an image has at most ``max_coarse``
    unknowns; that level is solved exactly by a float64 dense Cholesky factorisation of ``A_c +
    coarse_shift * diag(A_c)`` (eigenvalues clipped if round-off made it indefinite).

    Each level is smoothed by a Chebyshev polynomial of degree ``degree`` in ``D^{-1} A`` on
    ``[lambda_max / cheb_ratio, lambda_max]`` (the same polynomial before and after the coarse
    correction), so the V-cycle is a fixed symmetric positive definite operator.

    ``coarse_shift``: the shading matrix is singular up to its anchor (``1e-8`` of the mean
    diagonal, below float32 resolution), so an exact coarse solve would amplify the float32
    round-off of the residual's constant component by ``~1e8`` and PCG would stagnate.
    Shifting the coarsest diagonal by a relative ``1e-5`` leaves every other mode alone; the
    constant mode itself is already right in the cold start (``Psi 1 = 0``).

    The set-up (Galerkin products) runs in ``setup_dtype`` (default: the operator's dtype;
    with the shift above, float32 products lose nothing measurable and halve the set-up time);
    the cycle runs in the dtype of the operator it was built from. ``setup_time``: seconds of
    the set-up (with :meth:`from_system`, the operator's assembly included).

    Args:
        op: the fine operator (:class:`StencilOperator`, e.g. from
            :meth:`StencilOperator.from_quadratic` or :meth:`from_system`).
        block: aggregate side (3; 2 makes the coarse stencils grow).
        degree: Chebyshev degree of each pre-/post-smoothing.
        max_coarse: largest coarsest grid (unknowns per image) solved densely.
        max_levels: cap on the number of levels.
        power_iters: Lanczos steps estimating ``lambda_max`` per level.
        setup_dtype: dtype of the Galerkin products (``None``: the operator's).
        coarse_shift: relative diagonal shift of the coarsest matrix (see above).
        prolong_omega: prolongation smoothing ``omega * lambda_max(D_l^{-1} A_l)``.
        cheb_ratio: Chebyshev interval ``[lambda_max / cheb_ratio, lambda_max]``.

    Apply with ``M(r)`` / :meth:`apply` on ``(B, 1, H, W)`` residuals (any extra channel
    dimension is treated as independent vectors).
    """

    def __init__(
        self,
        op: StencilOperator,
        block: int = 3,
        degree: int = 3,
        max_coarse: int = 1500,
        max_levels: int = 12,
        power_iters: int = 15,
        setup_dtype: torch.dtype | None = None,
        coarse_shift: float = 1e-5,
        prolong_omega: float = 4.0 / 3.0,
        cheb_ratio: float = 30.0,
    ) -> None:
        if block < 2:
            raise ValueError(f"block must be >= 2, got {block}")
        if degree < 1:
            raise ValueError(f"degree must be >= 1, got {degree}")
        t0 = time.perf_counter()
        self.block, self.degree = int(block), int(degree)
        self.coarse_shift = float(coarse_shift)
        self.cheb_ratio = float(cheb_ratio)
        self.work_dtype = op.dtype
        self.levels: list[Level] = []
        cur = op.to(dtype=setup_dtype or op.dtype)
        while True:
            last = cur.numel <= max_coarse or len(self.levels) + 1 >= max_levels
            last = last or min(cur.height, cur.width) < 2 * block
            work = cur.to(dtype=self.work_dtype)
            dinv = 1 / work.diagonal()
            full_dinv = 1 / cur.diagonal()
            lmax = 1.1 * lanczos_lmax(cur.matvec, full_dinv, power_iters).to(self.work_dtype)
            lev = Level(work, dinv, lmax)
            self.levels.append(lev)
            if last:
                break
            transfer = aggregation(cur, self.block, power_iters, prolong_omega)
            coarse = galerkin(cur, transfer)
            lev.transfer = transfer.to(self.work_dtype)
            cur = coarse
        self._coarse = self._coarse_factor(cur)
        self.setup_time = time.perf_counter() - t0

    @classmethod
    def _for_system(cls, system: System, options: dict[str, Any]) -> Self:
        return cls(StencilOperator.from_quadratic(*system), **options)

    # -- transfer operators -----------------------------------------------------------------
    def _transfer(self, level: int) -> Transfer:
        tr = self.levels[level].transfer
        if tr is None:
            raise ShapeError(f"level {level} is the coarsest: it has no coarser level")
        return tr

    def prolong(self, level: int, xc: torch.Tensor) -> torch.Tensor:
        """``P_level xc``: coarse ``(B, C, Hc, Wc)`` to the grid of ``level``."""
        return self._transfer(level).prolong(xc)

    def restrict(self, level: int, r: torch.Tensor) -> torch.Tensor:
        """``P_level^T r``."""
        return self._transfer(level).restrict(r)

    # -- coarse solve ----------------------------------------------------------------------
    def _coarse_factor(self, op: StencilOperator) -> DenseSPD:
        dense = op.to(dtype=torch.float64).to_dense()
        if self.coarse_shift > 0:
            ar = torch.arange(dense.shape[-1], device=dense.device)
            dense[:, ar, ar] *= 1 + self.coarse_shift
        return DenseSPD(dense)

    def _coarse_solve(self, r: torch.Tensor) -> torch.Tensor:
        b, c, h, w = r.shape
        rhs = r.to(torch.float64).reshape(b, c, h * w).transpose(1, 2)
        x = self._coarse.solve(rhs)
        return x.transpose(1, 2).reshape(b, c, h, w).to(r.dtype)

    # -- cycle ------------------------------------------------------------------------------
    def _smooth(self, lev: Level, b: torch.Tensor, x: torch.Tensor | None) -> torch.Tensor:
        interval = (lev.lmax, self.cheb_ratio)
        return chebyshev(lev.op.matvec, lev.dinv, interval, self.degree, b, x)

    def _cycle(self, level: int, b: torch.Tensor) -> torch.Tensor:
        if level == len(self.levels) - 1:
            return self._coarse_solve(b)
        lev = self.levels[level]
        x = self._smooth(lev, b, None)
        r = b - lev.op.matvec(x)
        x = x + self.prolong(level, self._cycle(level + 1, self.restrict(level, r)))
        return self._smooth(lev, b, x)

    def apply(self, r: torch.Tensor) -> torch.Tensor:
        """``M^{-1} r`` (one V-cycle) for ``r`` ``(B, 1, H, W)`` (or ``(B, C, H, W)``)."""
        op = self.levels[0].op
        if r.shape[0] != op.batch or r.shape[-2:] != (op.height, op.width):
            raise ShapeError(
                f"expected (B={op.batch}, C, {op.height}, {op.width}), got {tuple(r.shape)}"
            )
        return self._cycle(0, r.to(self.work_dtype)).to(r.dtype)

    __call__ = apply

    # -- reporting ------------------------------------------------------------------------
    @property
    def grid_sizes(self) -> list[tuple[int, int]]:
        """``(H, W)`` of every level, finest first."""
        return [(lv.op.height, lv.op.width) for lv in self.levels]

    def operator_complexity(self) -> float:
        """Stored coefficients of all levels over the finest level's."""

        def size(op: StencilOperator) -> int:
            return op.a.numel() * 2 + op.d.numel() + sum(m._nnz() for m, _ in op.factors)

        return sum(size(lv.op) for lv in self.levels) / size(self.levels[0].op)
