"""Batched preconditioned conjugate gradient in torch (CPU or CUDA).

Solves ``A x = b`` for symmetric positive (semi-)definite ``A`` given only as a function
``matvec(x)``. The first dimension of ``b`` is the batch: each image has its own step sizes,
residual and stopping test, so a batch gives the same answer as its images one by one.
An item is declared converged only when its *true* residual ``||b - A x|| / ||b||`` is below
``tol`` (the recursive residual drifts in float32; on a mismatch CG restarts from the true
residual), and a :class:`ConvergenceWarning` is emitted otherwise, never a silent stop.

:func:`pcg` is the solver of the pipeline; :func:`pcg_callable` runs the same iteration and
also records the residual of every iteration (:class:`PCGHistory`), for comparing
preconditioners. On the CPU with a Jacobi preconditioner (or none) the iteration's vector
work runs as three fused compiled passes (:mod:`torchiid.solvers.pcg_fused`); elsewhere, and
with ``TORCHIID_KERNELS=torch``, as torch ops.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from torchiid.core.check import check_finite, check_shape
from torchiid.core.exceptions import ConvergenceWarning, ShapeError
from torchiid.solvers import pcg_fused

__all__ = ["PCGResult", "pcg", "PCGHistory", "pcg_callable"]

#: ``x -> A x`` (or ``r -> M^{-1} r``) on a batch shaped like the right-hand side
Operator = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class PCGResult:
    """Result of :func:`pcg`.

    Attributes:
        x: the solution, shaped like ``b``.
        iterations: iterations run (the batch's maximum).
        residual: ``(B,)`` final relative residual ``||b - A x|| / ||b||`` per batch item.
        converged: whether every batch item reached the tolerance (confirmed on the true
            residual; an item whose ``p^T A p <= 0`` is stopped and counts as not converged).
        item_iterations: ``(B,)`` iterations each batch item ran before it stopped.
        r: the residual ``b − A x`` at the end, shaped like ``b``: the true one with
            ``true_residual`` and for items that reached the tolerance, else the one CG
            carried (recursive). A later solve with the same ``A`` and a new right-hand side
            ``b'`` from ``x`` can start from ``r + (b' − b)`` (``r0=``) instead of a product.
    """

    x: torch.Tensor
    iterations: int
    residual: torch.Tensor
    converged: bool
    item_iterations: torch.Tensor | None = None
    r: torch.Tensor | None = None


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
    # a row-wise reduction: each item's sum is independent of the batch size (bmm is not)
    return (a * b).flatten(1).sum(dim=1)


def _bview(v: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return v.view(-1, *([1] * (like.dim() - 1)))


def _preconditioner(precond: torch.Tensor | Operator | None, b: torch.Tensor) -> Operator:
    """``r -> M^{-1} r`` for an inverse diagonal, a callable or ``None`` (identity)."""
    if precond is None:
        return lambda r: r
    if isinstance(precond, torch.Tensor):
        if precond.shape != b.shape:
            raise ShapeError(
                f"preconditioner has shape {tuple(precond.shape)}, expected {tuple(b.shape)}"
            )
        pinv = precond
        return lambda r: pinv * r
    return precond


def _start(b: torch.Tensor, x0: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The contiguous right-hand side and a private copy of the start (zeros by default)."""
    b = b.contiguous()
    x = torch.zeros_like(b) if x0 is None else x0.clone(memory_format=torch.contiguous_format)
    if x.shape != b.shape:
        raise ShapeError(f"x0 has shape {tuple(x.shape)} but b has shape {tuple(b.shape)}")
    return b, x


def _relative(r: torch.Tensor, bnorm: torch.Tensor) -> torch.Tensor:
    return _bdot(r, r).sqrt() / bnorm


@dataclass
class _Run:
    """A batched PCG iteration in progress (or done): what both solvers read."""

    x: torch.Tensor
    r: torch.Tensor
    bnorm: torch.Tensor
    res: torch.Tensor
    reached: torch.Tensor
    broke: torch.Tensor
    iters: torch.Tensor
    it: int = 0


#: called after every iteration with the iterate, the recursive relative residuals and the
#: items that were active during the iteration
Observer = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], None]


def _iterate(
    matvec: Operator,
    b: torch.Tensor,
    x: torch.Tensor,
    r: torch.Tensor,
    apply_m: Operator,
    limits: tuple[float, int],
    observe: Observer | None = None,
) -> _Run:
    """The PCG iteration from ``x`` with residual ``r`` (both updated in place).

    ``limits``: the relative tolerance and the iteration cap. Each item has its own step sizes
    and stops when its true residual is below the tolerance, or on breakdown (``p^T A p <=
    0``: ``A`` is not SPD on that item). Torch ops: any device, any preconditioner.
    """
    tol, max_iter = limits
    bnorm = _bdot(b, b).sqrt()
    bnorm = torch.where(bnorm > 0, bnorm, torch.ones_like(bnorm))
    z = apply_m(r)
    p = z.clone()
    rz = _bdot(r, z)
    res = _relative(r, bnorm)
    active = res > tol
    iters = torch.zeros(b.shape[0], dtype=torch.long, device=b.device)
    run = _Run(x, r, bnorm, res, ~active, torch.zeros_like(active), iters)
    while run.it < max_iter and bool(active.any()):
        ap = matvec(p)
        check_shape(ap, tuple(p.shape), pcg_fused.PRODUCT)
        pap = _bdot(p, ap)
        ok = pap > 0
        alpha = torch.where(active & ok, rz / torch.where(ok, pap, 1), 0)
        x.addcmul_(_bview(alpha, x), p)  # x, r and p are private: update in place
        run.r.addcmul_(_bview(alpha, run.r), ap, value=-1)
        z = apply_m(run.r)
        rz_new = _bdot(run.r, z)
        beta = torch.where(active & (rz > 0), rz_new / torch.where(rz > 0, rz, 1), 0)
        p.mul_(_bview(beta, p)).add_(z)
        rz = rz_new
        run.res = _relative(run.r, bnorm)
        run.iters = run.iters + active.long()
        run.it += 1
        if observe is not None:
            observe(x, run.res, active)
        # breakdown (pap <= 0 or NaN): A is not SPD on this item; stop it, do not claim success
        run.broke = run.broke | (active & ~ok)
        done = active & ok & ~(run.res > tol)
        if bool(done.any()):
            # residual replacement: the recursive residual drifts in float32, so confirm
            # with the true one and restart the direction where it is not yet reached
            r_true = b - matvec(x)
            res_true = _relative(r_true, bnorm)
            redo = done & (res_true > tol)
            # the finished items keep their true residual (what PCGResult.r hands on)
            run.r = torch.where(_bview(done, run.r), r_true, run.r)
            if bool(redo.any()):
                z_true = apply_m(run.r)
                p = torch.where(_bview(redo, p), z_true, p)
                rz = torch.where(redo, _bdot(run.r, z_true), rz)
                run.res = torch.where(redo, res_true, run.res)
            run.reached = run.reached | (done & ~redo)
        active = active & ~run.reached & ~run.broke
    return run


def _run(
    matvec: Operator,
    b: torch.Tensor,
    x: torch.Tensor,
    r: torch.Tensor,
    precond: tuple[torch.Tensor | Operator | None, Operator],
    limits: tuple[float, int],
    observe: Observer | None = None,
) -> _Run:
    """The iteration: fused compiled passes where they apply, else torch ops.

    ``precond``: the preconditioner as given and as an operator (see
    :mod:`~torchiid.solvers.pcg_fused`).
    """
    if pcg_fused.applies(precond[0], b, x, r):
        tensor = precond[0] if isinstance(precond[0], torch.Tensor) else None
        state, it = pcg_fused.iterate(matvec, b, x, r.contiguous(), tensor, limits, observe)
        r, bnorm, res, reached, broke, iters = state
        return _Run(x, r, bnorm, res, reached, broke, iters, it)
    return _iterate(matvec, b, x, r, precond[1], limits, observe)


def pcg(
    matvec: Operator,
    b: torch.Tensor,
    x0: torch.Tensor | None = None,
    precond: torch.Tensor | Operator | None = None,
    tol: float = 1e-5,
    max_iter: int = 500,
    warn: bool = True,
    true_residual: bool = True,
    r0: torch.Tensor | None = None,
) -> PCGResult:
    """Batched preconditioned conjugate gradient.

    Args:
        matvec: ``x -> A x`` for a batch ``x`` shaped like ``b``; ``A`` must be SPD on the
            space the iterates visit.
        b: right-hand side ``(B, ...)``.
        x0: warm start, shaped like ``b`` (default zeros).
        precond: the inverse diagonal (Jacobi) as a tensor shaped like ``b``, or a function
            applying ``M^{-1}``; ``None`` for plain CG.
        tol: stop a batch item when ``||r|| <= tol * ||b||``.
        max_iter: iteration cap.
        warn: emit :class:`ConvergenceWarning` when an item misses ``tol``.
        true_residual: recompute ``b - A x`` after the last iteration for the reported
            ``residual`` (one extra product). ``False`` reports the recursive residual, for
            callers that run a fixed, small number of iterations (inner solves) and do not
            need the exact figure; convergence is still confirmed on the true residual.
        r0: the residual ``b − A x0`` when the caller already has it (e.g. from the last
            solve's :attr:`PCGResult.r`), saving the first product; shaped like ``b``.

    Raises:
        ShapeError: ``x0`` or the preconditioner is not shaped like ``b``, or ``matvec``
            returns another shape than its input's.
        ImageError: ``b`` or ``x0`` holds NaN or infinite values.

    Returns:
        :class:`PCGResult`.
    """
    if b.dim() < 1 or b.shape[0] == 0:
        raise ShapeError(f"expected a batched right-hand side (B, ...), got {tuple(b.shape)}")
    b, x = _start(b, x0)
    apply_m = _preconditioner(precond, b)
    check_finite(b, "right-hand side b")
    check_finite(x, "warm start x0")
    if r0 is None:
        r = b - matvec(x)
    else:
        if r0.shape != b.shape:
            raise ShapeError(f"r0 has shape {tuple(r0.shape)} but b has shape {tuple(b.shape)}")
        r = r0.clone(memory_format=torch.contiguous_format)
        check_finite(r, "start residual r0")
    run = _run(matvec, b, x, r, (precond, apply_m), (tol, max_iter))
    converged = bool(run.reached.all())
    r, res = run.r, run.res
    if true_residual:
        # report the true residual (the recursive one drifts in float32)
        r = b - matvec(x)
        res = _relative(r, run.bnorm)
    if warn and not converged:
        why = " (breakdown: the operator is not positive definite)" if bool(run.broke.any()) else ""
        warnings.warn(
            f"PCG stopped after {run.it} iterations with relative residual "
            f"{float(res.max()):.3g} > tol {tol:g}{why}",
            ConvergenceWarning,
            stacklevel=2,
        )
    return PCGResult(
        x=x, iterations=run.it, residual=res, converged=converged, item_iterations=run.iters, r=r
    )


def pcg_callable(
    matvec: Operator,
    b: torch.Tensor,
    x0: torch.Tensor | None = None,
    precond: Operator | torch.Tensor | None = None,
    tol: float = 1e-5,
    max_iter: int = 500,
    snapshot_tols: Sequence[float] = (),
) -> PCGHistory:
    """Batched preconditioned CG recording the relative residual of every iteration.

    The iteration of :func:`pcg` (per-item step sizes and stopping, a true-residual check
    with restart where the recursive residual drifted); ``precond`` is a callable ``r ->
    M^{-1} r`` (e.g. a :class:`~torchiid.solvers.multigrid.GalerkinMultigrid`), an inverse
    diagonal tensor shaped like ``b``, or ``None``. It never warns: the history tells.

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
    b, x = _start(b, x0)
    apply_m = _preconditioner(precond, b)
    r = b - matvec(x)
    hist: list[torch.Tensor] = []
    snaps: dict[float, torch.Tensor] = {}
    pending = sorted({float(t) for t in snapshot_tols}, reverse=True)

    def observe(x: torch.Tensor, res: torch.Tensor, active: torch.Tensor) -> None:
        # an item keeps the residual it stopped at
        hist.append(torch.where(active, res, hist[-1]))
        while pending and bool((hist[-1] <= pending[0]).all()):
            snaps[pending.pop(0)] = x.clone()

    bnorm = _bdot(b, b).sqrt()
    hist.append(_relative(r, torch.where(bnorm > 0, bnorm, torch.ones_like(bnorm))))
    run = _run(matvec, b, x, r, (precond, apply_m), (tol, max_iter), observe)
    res_true = _relative(b - matvec(x), run.bnorm)
    final = {t: x.clone() for t in pending if bool((res_true <= t).all())}
    return PCGHistory(
        x=x,
        iterations=run.it,
        residual=res_true,
        converged=bool((res_true <= tol * 1.0001).all()) and bool(run.reached.all()),
        history=torch.stack(hist),
        item_iterations=run.iters,
        snapshots={**final, **snaps},
    )
