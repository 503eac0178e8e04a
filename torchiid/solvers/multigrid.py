"""Multigrid preconditioners for the shading solve, and a PCG that records its history.

The shading system ``A = D_m Psi D_m + diag(extra)`` (Eq. 1 plus the gauge anchor and the pinning
of masked-out pixels, see :func:`~torchiid.stages.shading.anchored_system`) is a 5x5-stencil graph
Laplacian with near-binary, strongly discontinuous weights (Retinex ``t_c = 1e-4``), a few small
positive off-diagonals (the matting Laplacian) and a handful of non-local rows (the LLE term
``S_c``).
Jacobi-preconditioned CG needs hundreds to thousands of iterations on it. Two multigrid
V-cycles bring that to about ten; both are fixed, symmetric positive definite linear operators,
so plain (non-flexible) PCG stays valid:

* :class:`GalerkinMultigrid` -- torch only (CPU or CUDA, batched). Geometric 3x3 aggregation
  with a prolongation smoothed by one damped-Jacobi step of the *local* stencil (smoothed
  aggregation), exact Galerkin coarse operators ``A_c = P^T A P`` kept as 5x5 stencils (computed
  by probing with 25 coloured vectors), the non-local rows kept in factored form
  ``(M P)^T W (M P)`` (they would otherwise fill the coarse matrices), Chebyshev smoothing and
  a dense Cholesky solve (float64) on the coarsest grid. Every operation is a shifted
  elementwise product or a tiny sparse product: no sparse matrix of the image is ever assembled.
* :class:`AMGPreconditioner` -- pyamg smoothed aggregation on the assembled scipy CSR matrix
  (CPU only), applied as one V-cycle to torch tensors.

:class:`HSCPreconditioner` is the hierarchical "sparsify and compensate" preconditioner of
Krishnan, Fattal & Szeliski (SIGGRAPH 2013) in a simplified algebraic form (see its notes).

:func:`pcg_callable` is batched PCG with a callable preconditioner that also returns the
residual history (the library's :func:`torchiid.solvers.pcg.pcg` accepts a callable too, but
records no history).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

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

__all__ = [
    "StencilOperator",
    "GalerkinMultigrid",
    "AMGPreconditioner",
    "HSCPreconditioner",
    "assemble_csr",
    "PCGHistory",
    "pcg_callable",
]


# ---------------------------------------------------------------------------------------------
# the anchored system of solve_shading
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# PCG with a callable preconditioner and residual history
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PCGHistory:
    """Result of :func:`pcg_callable`.

    Attributes:
        x: the solution, shaped like ``b``.
        iterations: iterations run (the batch's maximum).
        residual: ``(B,)`` final true relative residual ``||b - A x|| / ||b||``.
        converged: whether every item reached ``tol`` (on the true residual).
        history: ``(iterations + 1, B)`` recursive relative residual after each iteration
            (row 0: the start).
        item_iterations: ``(B,)`` iterations each item ran.
        snapshots: tolerance -> the iterate when every item first reached it (see
            ``snapshot_tols``).
    """

    x: torch.Tensor
    iterations: int
    residual: torch.Tensor
    converged: bool
    history: torch.Tensor
    item_iterations: torch.Tensor = field(default_factory=lambda: torch.zeros(0))
    snapshots: dict[float, torch.Tensor] = field(default_factory=dict)

    def iterations_to(self, tol: float) -> int:
        """First iteration at which every item's recorded residual is ``<= tol`` (-1: never)."""
        ok = (self.history <= tol).all(dim=1).nonzero()
        return int(ok[0, 0]) if ok.numel() else -1


def _bdot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).flatten(1).sum(dim=1)


def _bview(v: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return v.view(-1, *([1] * (like.dim() - 1)))


def pcg_callable(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    x0: torch.Tensor | None = None,
    precond: Callable[[torch.Tensor], torch.Tensor] | torch.Tensor | None = None,
    tol: float = 1e-5,
    max_iter: int = 500,
    snapshot_tols: Sequence[float] = (),
) -> PCGHistory:
    """Batched preconditioned CG recording the relative residual of every iteration.

    Same iteration as :func:`torchiid.solvers.pcg.pcg` (per-item step sizes and stopping, a
    final true-residual check with restart where the recursive residual drifted); ``precond``
    is a callable ``r -> M^{-1} r`` (e.g. a :class:`GalerkinMultigrid`), an inverse diagonal
    tensor, or ``None``.

    Args:
        matvec: ``x -> A x``.
        b: ``(B, ...)`` right-hand side.
        x0: warm start (default zeros).
        precond: the preconditioner.
        tol: relative residual tolerance.
        max_iter: iteration cap.
        snapshot_tols: also keep a copy of the iterate when the (recursive) residual of every
            item first drops to each of these tolerances (``PCGHistory.snapshots``).

    Returns:
        :class:`PCGHistory`.
    """
    b = b.contiguous()
    x = torch.zeros_like(b) if x0 is None else x0.clone(memory_format=torch.contiguous_format)
    if x.shape != b.shape:
        raise ShapeError(f"x0 has shape {tuple(x.shape)} but b has shape {tuple(b.shape)}")
    if precond is None:

        def apply_m(r: torch.Tensor) -> torch.Tensor:
            return r.clone()
    elif isinstance(precond, torch.Tensor):
        pinv = precond

        def apply_m(r: torch.Tensor) -> torch.Tensor:
            return pinv * r
    else:
        apply_m = precond
    bnorm = _bdot(b, b).sqrt()
    bnorm = torch.where(bnorm > 0, bnorm, torch.ones_like(bnorm))
    r = b - matvec(x)
    z = apply_m(r)
    p = z.clone()
    rz = _bdot(r, z)
    res = _bdot(r, r).sqrt() / bnorm
    hist = [res.clone()]
    snaps: dict[float, torch.Tensor] = {}
    pending = sorted({float(t) for t in snapshot_tols}, reverse=True)
    active = res > tol
    reached = ~active
    iters = torch.zeros(b.shape[0], dtype=torch.long, device=b.device)
    it = 0
    while it < max_iter and bool(active.any()):
        ap = matvec(p)
        pap = _bdot(p, ap)
        ok = pap > 0
        alpha = torch.where(active & ok, rz / torch.where(ok, pap, 1), 0)
        x.addcmul_(_bview(alpha, x), p)
        r.addcmul_(_bview(alpha, r), ap, value=-1)
        z = apply_m(r)
        rz_new = _bdot(r, z)
        beta = torch.where(active & (rz > 0), rz_new / torch.where(rz > 0, rz, 1), 0)
        p.mul_(_bview(beta, p)).add_(z)
        rz = rz_new
        res = torch.where(active, _bdot(r, r).sqrt() / bnorm, res)
        iters = iters + active.long()
        it += 1
        hist.append(res.clone())
        while pending and bool((res <= pending[0]).all()):
            snaps[pending.pop(0)] = x.clone()
        active = active & ok
        done = active & ~(res > tol)
        if bool(done.any()):
            r_true = b - matvec(x)
            res_true = _bdot(r_true, r_true).sqrt() / bnorm
            redo = done & (res_true > tol)
            if bool(redo.any()):
                rv = _bview(redo, r)
                r = torch.where(rv, r_true, r)
                z_true = apply_m(r)
                p = torch.where(rv, z_true, p)
                rz = torch.where(redo, _bdot(r, z_true), rz)
                res = torch.where(redo, res_true, res)
            reached = reached | (done & ~redo)
        active = active & ~reached
    r_true = b - matvec(x)
    res_true = _bdot(r_true, r_true).sqrt() / bnorm
    return PCGHistory(
        x=x,
        iterations=it,
        residual=res_true,
        converged=bool((res_true <= tol * 1.0001).all()) and bool(reached.all()),
        history=torch.stack(hist),
        item_iterations=iters,
        snapshots={**{t: x.clone() for t in pending if bool((res_true <= t).all())}, **snaps},
    )


# ---------------------------------------------------------------------------------------------
# stencil operators
# ---------------------------------------------------------------------------------------------


def _half(o: tuple[int, int]) -> bool:
    return o[0] > 0 or (o[0] == 0 and o[1] > 0)


def _square_half_offsets(radius: int) -> list[tuple[int, int]]:
    return [
        (dy, dx)
        for dy in range(0, radius + 1)
        for dx in range(-radius, radius + 1)
        if _half((dy, dx))
    ]


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
        factors: Sequence[tuple[torch.Tensor, torch.Tensor]] = (),
    ) -> None:
        self.offsets = [(int(dy), int(dx)) for dy, dx in offsets]
        if any(not _half(o) for o in self.offsets):
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
        self._ops = []
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

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None):
        """A copy with coefficients converted (``StencilOperator``)."""
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

    def to_scipy(self):  # noqa: ANN201
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
        m = None if mask is None else mask.to(device=dev, dtype=dt).reshape(b, 1, h, w)
        offsets: list[tuple[int, int]] = []
        for _, t in terms:
            if isinstance(t, StencilQuadratic):
                for o in t.stencil.offsets:
                    if not _half(o):
                        raise ShapeError(f"stencil offset {o} is not a half offset")
                    if o not in offsets:
                        offsets.append(o)
        offsets.sort()
        pos = {o: k for k, o in enumerate(offsets)}
        a = torch.zeros(b, len(offsets), h, w, dtype=dt, device=dev)
        d = torch.zeros(b, 1, h, w, dtype=dt, device=dev)
        factors: list[tuple[torch.Tensor, torch.Tensor]] = []
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
        if m is not None:
            for k, (dy, dx) in enumerate(offsets):
                yi, xi, yj, xj = shift_slices(dy, dx, h, w)
                a[:, k, yi, xi] *= m[:, 0, yi, xi] * m[:, 0, yj, xj]
            d = d * m
            mf = m.reshape(-1)
            masked = []
            for mm, wr in factors:  # M D_m: drop the columns of pixels outside
                mm = mm.coalesce()
                idx = mm.indices()
                vals = mm.values() * mf[idx[1]]
                masked.append(
                    (torch.sparse_coo_tensor(idx, vals, mm.shape, check_invariants=False), wr)
                )
            factors = masked
        if extra_diag is not None:
            d = d + extra_diag.to(device=dev, dtype=dt).reshape(b, 1, h, w)
        return cls(offsets, a, d, factors)


# ---------------------------------------------------------------------------------------------
# torch multigrid: geometric aggregation, smoothed prolongation, Galerkin by probing
# ---------------------------------------------------------------------------------------------


class _DenseSPD:
    """Solves with a batch ``(B, n, n)`` of dense symmetric PSD matrices (float64).

    Cholesky; where round-off made a (near-singular) matrix indefinite, a clipped
    eigendecomposition instead (eigenvalues below ``1e-13 * lambda_max`` raised to it), so the
    solve is always an SPD operator.
    """

    def __init__(self, dense: torch.Tensor) -> None:
        dense = 0.5 * (dense + dense.transpose(-1, -2)).to(torch.float64)
        self.chol, info = torch.linalg.cholesky_ex(dense)
        self.eig = None
        if bool((info != 0).any()):
            ev, vec = torch.linalg.eigh(dense)
            ev = torch.maximum(ev, ev[..., -1:].abs() * 1e-13)
            self.eig = (vec, 1 / ev)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """``A^{-1} rhs`` for ``rhs`` ``(B, n, k)``."""
        rhs = rhs.to(torch.float64)
        if self.eig is not None:
            vec, inv = self.eig
            return vec @ (inv.unsqueeze(-1) * (vec.transpose(-1, -2) @ rhs))
        return torch.cholesky_solve(rhs, self.chol)


def _lanczos_lmax(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    dinv: torch.Tensor,
    iters: int,
    seed: int = 0,
) -> torch.Tensor:
    """Per-item estimate ``(B, 1, 1, 1)`` of the largest eigenvalue of ``D^{-1} A``.

    ``iters`` Lanczos steps on the symmetric ``D^{-1/2} A D^{-1/2}`` (same spectrum) from a
    zero-mean random start; the estimate is the largest eigenvalue of the Lanczos
    tridiagonal, which never exceeds the true one (callers add a margin). It replaced a power
    iteration from a mostly constant start, which converges slowly where the top of the
    spectrum is dense: on a photo's shading system (a 512×384 JPEG of chelsea) its 15 steps
    gave 1.86 on the second level against 2.28 after 200 steps, and the Chebyshev smoother,
    tuned to ``1.1 × 1.86``, amplified the modes above it: 97 multigrid-PCG iterations instead
    of 14 (the mirrored photo: 14 either way).
    """
    g = torch.Generator(device="cpu").manual_seed(seed)
    s = dinv.clamp_min(0).sqrt()
    b = dinv.shape[0]
    # the same start for every item: a batch gives its items' one-by-one preconditioners
    x = torch.rand((1, *dinv.shape[1:]), generator=g, dtype=torch.float64) - 0.5
    q = x.to(dinv).expand_as(dinv).contiguous()
    q = q / q.flatten(1).norm(dim=1).clamp_min(torch.finfo(q.dtype).tiny).view(-1, 1, 1, 1)
    q_prev = torch.zeros_like(q)
    beta = torch.zeros(b, 1, 1, 1, dtype=q.dtype, device=q.device)
    alphas, betas = [], []
    for _ in range(max(1, iters)):
        w = s * matvec(s * q)
        alpha = (w * q).flatten(1).sum(1).view(-1, 1, 1, 1)
        w = w - alpha * q - beta * q_prev
        beta = w.flatten(1).norm(dim=1).view(-1, 1, 1, 1)
        alphas.append(alpha.flatten())
        betas.append(beta.flatten())
        # an exhausted Krylov space (beta ~ 0) is exact: that item's later steps add zeros
        live = beta > 1e-6 * alpha.abs().clamp_min(torch.finfo(q.dtype).tiny)
        q_prev, q = q, torch.where(live, w / beta.clamp_min(torch.finfo(q.dtype).tiny), 0)
        beta = torch.where(live, beta, 0)
    a = torch.stack(alphas, dim=1).to(torch.float64).cpu()  # (B, k)
    off = torch.stack(betas[:-1], dim=1).to(torch.float64).cpu() if len(betas) > 1 else None
    t = torch.diag_embed(a)
    if off is not None:
        t = t + torch.diag_embed(off, offset=1) + torch.diag_embed(off, offset=-1)
    lam = torch.linalg.eigvalsh(t)[:, -1]
    return lam.to(dtype=dinv.dtype, device=dinv.device).view(-1, 1, 1, 1)


@dataclass
class _Level:
    op: StencilOperator  # the full operator of this level (working dtype)
    dinv: torch.Tensor  # 1 / diag(op)
    lmax: torch.Tensor  # (B,1,1,1) estimate of lambda_max(D^-1 A), with margin
    # transfer to the next coarser level (None on the coarsest)
    local: StencilOperator | None = None  # the stencil used to smooth the prolongation
    dloc_inv: torch.Tensor | None = None
    omega: torch.Tensor | None = None
    coarse_shape: tuple[int, int] | None = None


class GalerkinMultigrid:
    """Torch-only smoothed-aggregation multigrid V-cycle, an SPD preconditioner.

    Hierarchy: pixels are aggregated in ``block x block`` squares (the coarse grid is again an
    image), the tentative prolongation ``P_t`` is piecewise constant and is smoothed once,
    ``P = (I - omega D_l^{-1} A_l) P_t`` with ``omega = 4/3 / lambda_max(D_l^{-1} A_l)``, using only
    the *local* (stencil) part ``A_l`` of the level's operator so ``P`` stays local. The coarse
    operator is the exact Galerkin product ``A_c = P^T A P``: its stencil part (radius
    ``floor((3 r + block - 1) / block)``, i.e. 5x5 stays 5x5 for ``block = 3``) is read off
    ``(2 r_c + 1)^2`` probe vectors, and the non-local rows ``M^T W M`` become ``(M P)^T W (M P)``
    (factored, so the few LLE rows never fill the coarse matrices). Coarsening stops when an
    image has at most ``max_coarse`` unknowns; that level is solved exactly by a float64 dense
    Cholesky factorisation of ``A_c + coarse_shift * diag(A_c)`` (eigenvalues clipped if
    round-off made it indefinite).

    Each level is smoothed by a Chebyshev polynomial of degree ``degree`` in ``D^{-1} A`` on
    ``[lambda_max / cheb_ratio, lambda_max]`` (the same polynomial before and after the coarse
    correction), so the V-cycle is a fixed symmetric positive definite operator.

    ``coarse_shift``: the shading matrix is singular up to its anchor (``1e-8`` of the mean
    diagonal, below float32 resolution), so an exact coarse solve amplifies the float32
    round-off of the residual's constant component by ``~1e8``; PCG then stagnates (measured:
    24 instead of 16 iterations to 1e-5 at 256x192). Shifting the coarsest diagonal by a
    relative ``1e-5`` leaves every other mode alone and restores the float64 iteration counts;
    the constant mode itself is already right in the cold start (``Psi 1 = 0``).

    The setup (Galerkin products) runs in ``setup_dtype`` (default: the operator's dtype; with
    the shift above float32 products lose nothing measurable and halve the setup time); the
    cycle runs in the dtype of the operator it was built from.

    Args:
        op: the fine operator (:class:`StencilOperator`, e.g. from
            :meth:`StencilOperator.from_quadratic` or :meth:`from_system`).
        block: aggregate side (3; 2 makes the coarse stencils grow).
        degree: Chebyshev degree of each pre-/post-smoothing.
        max_coarse: largest coarsest grid (unknowns per image) solved densely.
        max_levels: cap on the number of levels.
        power_iters: Lanczos steps estimating ``lambda_max`` per level (the name is that of
            the power iteration it replaced).
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
        self.levels: list[_Level] = []
        cur = op.to(dtype=setup_dtype or op.dtype)
        while True:
            last = cur.numel <= max_coarse or len(self.levels) + 1 >= max_levels
            last = last or min(cur.height, cur.width) < 2 * block
            work = cur.to(dtype=self.work_dtype)
            dinv = 1 / work.diagonal()
            full_dinv = 1 / cur.diagonal()
            lmax = 1.1 * _lanczos_lmax(cur.matvec, full_dinv, power_iters).to(self.work_dtype)
            lev = _Level(work, dinv, lmax)
            self.levels.append(lev)
            if last:
                break
            loc = cur.local()
            dl_inv = 1 / loc.d
            rho = _lanczos_lmax(loc.stencil_matvec, dl_inv, power_iters)
            omega = prolong_omega / rho
            hc, wc = -(-cur.height // block), -(-cur.width // block)
            coarse = self._galerkin(cur, loc, dl_inv, omega, (hc, wc))
            lev.local = loc.to(dtype=self.work_dtype)
            lev.dloc_inv = dl_inv.to(self.work_dtype)
            lev.omega = omega.to(self.work_dtype)
            lev.coarse_shape = (hc, wc)
            cur = coarse
        self._coarse_factor(cur)
        self.setup_time = time.perf_counter() - t0

    @classmethod
    def from_system(
        cls,
        total: QuadraticTerm,
        extra_diag: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        **kwargs: object,
    ) -> GalerkinMultigrid:
        """Build for ``D_m total D_m + diag(extra_diag)`` (what ``solve_shading`` solves)."""
        return cls(StencilOperator.from_quadratic(total, extra_diag, mask), **kwargs)

    # -- transfer operators -----------------------------------------------------------------
    def _up(self, xc: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
        s = self.block
        u = xc.repeat_interleave(s, dim=2).repeat_interleave(s, dim=3)
        return u[:, :, : shape[0], : shape[1]]

    def _sum_down(self, r: torch.Tensor, cshape: tuple[int, int]) -> torch.Tensor:
        s = self.block
        b, c, h, w = r.shape
        hc, wc = cshape
        if (h, w) != (hc * s, wc * s):
            r = torch.nn.functional.pad(r, (0, wc * s - w, 0, hc * s - h))
        return r.reshape(b, c, hc, s, wc, s).sum(dim=(3, 5))

    @staticmethod
    def _prolong(
        xc: torch.Tensor,
        up: Callable,
        loc: StencilOperator,
        dl_inv: torch.Tensor,
        omega: torch.Tensor,
    ) -> torch.Tensor:
        u = up(xc)
        return u - (omega * dl_inv) * loc.stencil_matvec(u)

    @staticmethod
    def _restrict(
        r: torch.Tensor,
        down: Callable,
        loc: StencilOperator,
        dl_inv: torch.Tensor,
        omega: torch.Tensor,
    ) -> torch.Tensor:
        return down(r - omega * loc.stencil_matvec(dl_inv * r))

    def prolong(self, level: int, xc: torch.Tensor) -> torch.Tensor:
        """``P_level xc``: coarse ``(B, C, Hc, Wc)`` to the grid of ``level``."""
        lev = self.levels[level]
        shape = (lev.op.height, lev.op.width)
        return self._prolong(xc, lambda v: self._up(v, shape), lev.local, lev.dloc_inv, lev.omega)

    def restrict(self, level: int, r: torch.Tensor) -> torch.Tensor:
        """``P_level^T r``."""
        lev = self.levels[level]
        return self._restrict(
            r, lambda v: self._sum_down(v, lev.coarse_shape), lev.local, lev.dloc_inv, lev.omega
        )

    # -- Galerkin product -------------------------------------------------------------------
    def _galerkin(
        self,
        op: StencilOperator,
        loc: StencilOperator,
        dl_inv: torch.Tensor,
        omega: torch.Tensor,
        cshape: tuple[int, int],
    ) -> StencilOperator:
        s = self.block
        h, w = op.height, op.width
        hc, wc = cshape
        b = op.batch
        dev, dt = op.device, op.dtype
        r = op.radius
        rc = max(1, (3 * r + s - 1) // s) if r > 0 else 1
        q = 2 * rc + 1

        def up(v: torch.Tensor) -> torch.Tensor:
            return self._up(v, (h, w))

        def down(v: torch.Tensor) -> torch.Tensor:
            return self._sum_down(v, cshape)

        yy = torch.arange(hc, device=dev).view(-1, 1)
        xx = torch.arange(wc, device=dev).view(1, -1)
        color = (yy % q) * q + (xx % q)  # (hc, wc)
        # probes in chunks of channels (memory: chunk * H * W per array)
        chunk = max(1, min(q * q, int(4e7 // max(1, b * h * w))))
        vals = torch.empty(b, q * q, hc, wc, dtype=dt, device=dev)
        for c0 in range(0, q * q, chunk):
            cs = torch.arange(c0, min(q * q, c0 + chunk), device=dev)
            e = (color.view(1, 1, hc, wc) == cs.view(1, -1, 1, 1)).to(dt).expand(b, -1, -1, -1)
            pe = self._prolong(e.contiguous(), up, loc, dl_inv, omega)
            vals[:, c0 : c0 + cs.numel()] = self._restrict(
                loc.stencil_matvec(pe), down, loc, dl_inv, omega
            )
        # read the stencil: A_c[I, I + o] = vals[color(I + o)][I]
        offsets = _square_half_offsets(rc)
        a = torch.zeros(b, len(offsets), hc, wc, dtype=dt, device=dev)
        for k, (dy, dx) in enumerate(offsets):
            yi, xi, yj, xj = shift_slices(dy, dx, hc, wc)
            if yi.stop <= yi.start or xi.stop <= xi.start:
                continue
            cj = color[yj, xj]  # colour of the partner I + o
            ci = color[yi, xi]  # colour of I
            fwd = vals[:, :, yi, xi].gather(1, cj.expand(b, 1, *cj.shape))
            bwd = vals[:, :, yj, xj].gather(1, ci.expand(b, 1, *ci.shape))
            a[:, k, yi, xi] = 0.5 * (fwd + bwd)[:, 0]
        d = vals.gather(1, color.expand(b, 1, hc, wc))
        factors = [
            self._factor_galerkin(m, wr, loc, dl_inv, omega, (h, w), cshape) for m, wr in op.factors
        ]
        return StencilOperator(offsets, a, d, factors)

    def _factor_galerkin(
        self,
        m: torch.Tensor,
        wr: torch.Tensor,
        loc: StencilOperator,
        dl_inv: torch.Tensor,
        omega: torch.Tensor,
        shape: tuple[int, int],
        cshape: tuple[int, int],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``M P`` for sparse rows ``M`` (exact, structured: no matrix of ``P`` is formed)."""
        s = self.block
        h, w = shape
        hc, wc = cshape
        n, nc = h * w, hc * wc
        m = m.coalesce()
        (rows, cols), v = m.indices(), m.values()
        bi = cols // n
        y, x = (cols % n) // w, cols % w

        def coarse_index(bb, yy_, xx_):  # noqa: ANN001, ANN202
            return bb * nc + (yy_ // s) * wc + (xx_ // s)

        out_r = [rows]
        out_c = [coarse_index(bi, y, x)]
        out_v = [v]
        # - omega M D^-1 A_l P_t: entry (r, J(i + o)) += -omega v / d_i * A_l[i, i + o]
        coef = -omega.reshape(-1)[bi] * v * dl_inv.reshape(-1)[cols]
        full = [((0, 0), None)] + [(o, (k, 1)) for k, o in enumerate(loc.offsets)]
        full += [((-o[0], -o[1]), (k, -1)) for k, o in enumerate(loc.offsets)]
        af = loc.a.reshape(loc.batch, len(loc.offsets), n)
        for (dy, dx), which in full:
            yj, xj = y + dy, x + dx
            inside = (yj >= 0) & (yj < h) & (xj >= 0) & (xj < w)
            if which is None:
                aij = loc.d.reshape(-1)[cols]
            else:
                k, sign = which
                src = cols % n if sign > 0 else ((yj.clamp(0, h - 1)) * w + xj.clamp(0, w - 1))
                aij = af[bi, k, src]
            keep = inside & (aij != 0)
            out_r.append(rows[keep])
            out_c.append(coarse_index(bi[keep], yj[keep], xj[keep]))
            out_v.append((coef * aij)[keep])
        mc = torch.sparse_coo_tensor(
            torch.stack([torch.cat(out_r), torch.cat(out_c)]),
            torch.cat(out_v),
            (m.shape[0], m.shape[1] // n * nc),
            check_invariants=False,
        ).coalesce()
        return mc, wr

    # -- coarse solve ----------------------------------------------------------------------
    def _coarse_factor(self, op: StencilOperator) -> None:
        dense = op.to(dtype=torch.float64).to_dense()
        if self.coarse_shift > 0:
            ar = torch.arange(dense.shape[-1], device=dense.device)
            dense[:, ar, ar] *= 1 + self.coarse_shift
        self._coarse = _DenseSPD(dense)

    def _coarse_solve(self, r: torch.Tensor) -> torch.Tensor:
        b, c, h, w = r.shape
        rhs = r.to(torch.float64).reshape(b, c, h * w).transpose(1, 2)
        x = self._coarse.solve(rhs)
        return x.transpose(1, 2).reshape(b, c, h, w).to(r.dtype)

    # -- smoothing and cycle ----------------------------------------------------------------
    def _chebyshev(self, lev: _Level, b: torch.Tensor, x: torch.Tensor | None) -> torch.Tensor:
        lmax = lev.lmax
        lmin = lmax / self.cheb_ratio
        theta = (lmax + lmin) / 2
        delta = (lmax - lmin) / 2
        sigma = theta / delta
        rho = 1 / sigma
        r = lev.dinv * (b if x is None else b - lev.op.matvec(x))
        dvec = r / theta
        x = dvec.clone() if x is None else x + dvec
        for _ in range(self.degree - 1):
            r = r - lev.dinv * lev.op.matvec(dvec)
            rho_new = 1 / (2 * sigma - rho)
            dvec = (rho_new * rho) * dvec + (2 * rho_new / delta) * r
            rho = rho_new
            x = x + dvec
        return x

    def _cycle(self, level: int, b: torch.Tensor) -> torch.Tensor:
        if level == len(self.levels) - 1:
            return self._coarse_solve(b)
        lev = self.levels[level]
        x = self._chebyshev(lev, b, None)
        r = b - lev.op.matvec(x)
        x = x + self.prolong(level, self._cycle(level + 1, self.restrict(level, r)))
        return self._chebyshev(lev, b, x)

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


# ---------------------------------------------------------------------------------------------
# scipy assembly and pyamg
# ---------------------------------------------------------------------------------------------


def assemble_csr(
    total: QuadraticTerm,
    extra_diag: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
):  # noqa: ANN201
    """``D_m total D_m + diag(extra_diag)`` as a scipy CSR float64 matrix (block-diagonal).

    Built from the stencil weights directly (no sort of the ``25 N`` entries as in
    ``total.to_sparse()``), about 10x faster; terms without a stencil or factored form fall
    back to their ``to_sparse()``.
    """
    import scipy.sparse as sp

    try:
        return StencilOperator.from_quadratic(total, extra_diag, mask, torch.float64).to_scipy()
    except ShapeError:
        pass
    a = total.to_sparse().coalesce()
    i, j = a.indices().cpu().numpy()
    mat = sp.csr_matrix((a.values().double().cpu().numpy(), (i, j)), shape=tuple(a.shape))
    if mask is not None:
        md = sp.diags(mask.double().cpu().numpy().reshape(-1))
        mat = md @ mat @ md
    if extra_diag is not None:
        mat = mat + sp.diags(extra_diag.double().cpu().numpy().reshape(-1))
    return mat.tocsr()


class _FromCSR:
    """``from_system`` of the preconditioners built from a scipy CSR matrix."""

    setup_time: float

    @classmethod
    def from_system(
        cls,
        total: QuadraticTerm,
        extra_diag: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        **kwargs: object,
    ):  # noqa: ANN206 (the subclass)
        """Assemble (:func:`assemble_csr`) and build; ``setup_time`` includes the assembly."""
        t0 = time.perf_counter()
        out = cls(assemble_csr(total, extra_diag, mask), total.shape, **kwargs)
        out.setup_time = time.perf_counter() - t0
        return out


class AMGPreconditioner(_FromCSR):
    """pyamg smoothed-aggregation V-cycle as a torch preconditioner (CPU).

    Settings chosen by measurement on the shading systems (256x192 to 1024x768, alternations
    1 and 3): symmetric strength of connection with a small threshold (``theta = 0.01``: the
    near-binary Retinex weights make the strength graph follow the image's edges;
    ``theta = 0``, pyamg's default, aggregates blindly across them and needs 2-3x more
    iterations), energy-minimising prolongation smoothing (with the strength filter it also
    keeps the LLE rows from filling the coarse levels), one symmetric Gauss-Seidel sweep before
    and after, coarse grids down to 500 unknowns solved by pseudo-inverse.

    Args:
        matrix: scipy sparse ``(B N, B N)`` (e.g. :func:`assemble_csr`) or torch sparse.
        shape: ``(B, 1, H, W)`` of the unknown.
        theta: strength threshold.
        smooth: pyamg prolongation smoother (``"energy"``, ``"jacobi"``, ...).
        presmoother: pyamg relaxation (post = same).
        max_coarse: coarsest size.
        cycle: ``"V"``, ``"W"`` or ``"F"``.
        dtype: numpy dtype of the hierarchy (float64 or float32).

    Apply with ``M(r)`` on a CPU tensor ``(B, 1, H, W)``; the result has ``r``'s dtype.
    """

    def __init__(
        self,
        matrix: object,
        shape: Sequence[int],
        theta: float = 0.01,
        smooth: object = "energy",
        presmoother: object = ("gauss_seidel", {"sweep": "symmetric"}),
        max_coarse: int = 500,
        cycle: str = "V",
        dtype: type = np.float64,
    ) -> None:
        import pyamg
        import scipy.sparse as sp

        t0 = time.perf_counter()
        if isinstance(matrix, torch.Tensor):
            a = matrix.coalesce()
            i, j = a.indices().cpu().numpy()
            matrix = sp.csr_matrix(
                (a.values().double().cpu().numpy(), (i, j)), shape=tuple(a.shape)
            )
        mat = sp.csr_matrix(matrix, dtype=dtype)
        self.shape = tuple(int(s) for s in shape)
        if mat.shape[0] != math.prod(self.shape):
            raise ShapeError(f"matrix of size {mat.shape[0]} does not fit shape {self.shape}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pyamg's sparse-efficiency and deprecation notes
            self.ml = pyamg.smoothed_aggregation_solver(
                mat,
                symmetry="symmetric",
                strength=("symmetric", {"theta": theta}),
                smooth=smooth,
                presmoother=presmoother,
                postsmoother=presmoother,
                max_coarse=max_coarse,
            )
        self._m = self.ml.aspreconditioner(cycle=cycle)
        self.dtype = dtype
        self.setup_time = time.perf_counter() - t0

    def apply(self, r: torch.Tensor) -> torch.Tensor:
        """``M^{-1} r`` for ``r`` ``(B, 1, H, W)`` (CPU)."""
        if tuple(r.shape) != self.shape:
            raise ShapeError(f"expected {self.shape}, got {tuple(r.shape)}")
        rn = r.detach().cpu().numpy().reshape(-1).astype(self.dtype)
        z = self._m @ rn
        return torch.from_numpy(np.asarray(z)).to(dtype=r.dtype, device=r.device).view(r.shape)

    __call__ = apply

    def operator_complexity(self) -> float:
        """Operator complexity of the pyamg hierarchy."""
        return float(self.ml.operator_complexity())


# ---------------------------------------------------------------------------------------------
# Krishnan, Fattal & Szeliski: hierarchical sparsify-and-compensate (HSC)
# ---------------------------------------------------------------------------------------------


def _compensate(w, drop_i, drop_j, drop_w, path_mask, factor):  # noqa: ANN001, ANN202
    """Remove edges ``(i, j, w)`` and re-route each along the 2-paths ``i - k - j`` of ``w``.

    The removed weight is spread over the common neighbours ``k`` allowed by ``path_mask``
    (bool per node) in proportion to the series conductances ``w_ik w_kj / (w_ik + w_kj)`` and
    added, times ``factor``, to both edges of each path (``factor = 2`` keeps the energy of a
    linear function whose path node is the edge's midpoint and makes the new Laplacian
    dominate the old one; ``factor = 1``, the default of :class:`HSCPreconditioner`, measured
    fewer PCG iterations). Edges without such a path are dropped. Returns the symmetric
    increment (scipy CSR) and the weight that found no path.
    """
    import scipy.sparse as sp

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


class HSCPreconditioner(_FromCSR):
    """Hierarchical sparsify-and-compensate preconditioner (Krishnan, Fattal & Szeliski 2013).

    Our algebraic reading of the paper for these image systems (CPU, scipy):

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
    exact weighting rules are not reproduced (only its abstract was available to us); the
    scheme above follows its description (sparsification of fine-fine connections and of
    fill, compensation by strengthening nearby connections, exact elimination).

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
        matrix: object,
        shape: Sequence[int],
        keep_radius: float = 2.0,
        factor: float = 1.0,
        max_coarse: int = 1500,
        coarse_shift: float = 1e-5,
    ) -> None:
        import scipy.sparse as sp

        t0 = time.perf_counter()
        self.shape = tuple(int(v) for v in shape)
        b, _, h, w = self.shape
        a = sp.csr_matrix(matrix, dtype=np.float64)
        n = a.shape[0]
        diag = a.diagonal()
        off = (a - sp.diags(diag)).tocsr()
        off.eliminate_zeros()
        pos = off.multiply(off > 0).tocsr()  # positive off-diagonals -> removed, to diagonals
        wts = (-(off - pos)).tocsr()  # edge weights >= 0
        ground = diag - np.asarray(wts.sum(axis=1)).ravel() + np.asarray(pos.sum(axis=1)).ravel()
        ground = np.maximum(ground, 0.0)
        idx = np.arange(n)
        yy = (idx % (h * w)) // w
        xx = idx % w
        img = idx // (h * w)
        self.levels: list[tuple] = []
        self.lost: list[float] = []
        nodes = idx  # global ids of the current level's nodes
        level = 0
        while True:
            m = len(nodes)
            if m <= max_coarse * b or level >= 40:
                break
            spacing = 2 ** (level // 2)
            ys, xs = yy[nodes] // spacing, xx[nodes] // spacing
            if level % 2 == 0:
                fine = (ys + xs) % 2 == 1
            else:
                fine = ys % 2 == 1
            if fine.all() or not fine.any():
                break
            # 3. sparsify F-F edges
            coo = sp.triu(wts, k=1).tocoo()
            ff = fine[coo.row] & fine[coo.col]
            lost = 0.0
            if ff.any():
                inc, lost = _compensate(wts, coo.row[ff], coo.col[ff], coo.data[ff], ~fine, factor)
                rm = sp.csr_matrix(
                    (
                        np.concatenate([coo.data[ff], coo.data[ff]]),
                        (
                            np.concatenate([coo.row[ff], coo.col[ff]]),
                            np.concatenate([coo.col[ff], coo.row[ff]]),
                        ),
                    ),
                    shape=wts.shape,
                )
                wts = (wts - rm + inc).tocsr()
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
            dy = (yy[cn[sc.row]] - yy[cn[sc.col]]) / (2 ** ((level + 1) / 2))
            dx = (xx[cn[sc.row]] - xx[cn[sc.col]]) / (2 ** ((level + 1) / 2))
            far = (dy * dy + dx * dx > keep_radius**2 + 1e-9) | (img[cn[sc.row]] != img[cn[sc.col]])
            if far.any():
                near_w = s_w.copy()
                rm = sp.csr_matrix(
                    (
                        np.concatenate([sc.data[far], sc.data[far]]),
                        (
                            np.concatenate([sc.row[far], sc.col[far]]),
                            np.concatenate([sc.col[far], sc.row[far]]),
                        ),
                    ),
                    shape=s_w.shape,
                )
                near_w = (near_w - rm).tocsr()
                near_w.eliminate_zeros()
                inc, lost2 = _compensate(
                    near_w,
                    sc.row[far],
                    sc.col[far],
                    sc.data[far],
                    np.ones(len(ci), dtype=bool),
                    factor,
                )
                s_w = (near_w + inc).tocsr()
                lost += lost2
            self.lost.append(lost)
            wts, ground, nodes = s_w, g_c, cn
            level += 1
        # coarsest: dense Cholesky of L(W) + diag(g)
        dense = -wts.toarray()
        np.fill_diagonal(dense, np.asarray(wts.sum(axis=1)).ravel() + ground)
        dense[np.diag_indices_from(dense)] *= 1 + coarse_shift
        self._coarse_nodes = nodes
        self._coarse = _DenseSPD(torch.from_numpy(dense)[None])
        self.setup_time = time.perf_counter() - t0

    def apply(self, r: torch.Tensor) -> torch.Tensor:
        """``M^{-1} r`` for ``r`` ``(B, 1, H, W)`` (CPU; computed in float64)."""
        if tuple(r.shape) != self.shape:
            raise ShapeError(f"expected {self.shape}, got {tuple(r.shape)}")
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
