"""Batched preconditioned conjugate gradient in torch (CPU or CUDA).

Solves ``A x = b`` for symmetric positive (semi-)definite ``A`` given only as a function
``matvec(x)``. The first dimension of ``b`` is the batch: each image has its own step sizes,
residual and stopping test, so a batch gives the same answer as its images one by one.
An item is declared converged only when its *true* residual ``||b - A x|| / ||b||`` is below
``tol`` (the recursive residual drifts in float32; on a mismatch CG restarts from the true
residual), and a :class:`ConvergenceWarning` is emitted otherwise, never a silent stop.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchiid.core.check import check_finite
from torchiid.core.exceptions import ConvergenceWarning, ShapeError

__all__ = ["PCGResult", "pcg"]


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


def _bdot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    # a row-wise reduction: each item's sum is independent of the batch size (bmm is not)
    return (a * b).flatten(1).sum(dim=1)


def _bview(v: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return v.view(-1, *([1] * (like.dim() - 1)))


def pcg(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    x0: torch.Tensor | None = None,
    precond: torch.Tensor | Callable[[torch.Tensor], torch.Tensor] | None = None,
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
        ShapeError: ``x0`` or the preconditioner is not shaped like ``b``.
        ImageError: ``b`` or ``x0`` holds NaN or infinite values.

    Returns:
        :class:`PCGResult`.
    """
    if b.dim() < 1 or b.shape[0] == 0:
        raise ShapeError(f"expected a batched right-hand side (B, ...), got {tuple(b.shape)}")
    b = b.contiguous()
    x = torch.zeros_like(b) if x0 is None else x0.clone(memory_format=torch.contiguous_format)
    if x.shape != b.shape:
        raise ShapeError(f"x0 has shape {tuple(x.shape)} but b has shape {tuple(b.shape)}")
    if precond is None:

        def apply_m(r: torch.Tensor) -> torch.Tensor:
            return r
    elif isinstance(precond, torch.Tensor):
        if precond.shape != b.shape:
            raise ShapeError(
                f"preconditioner has shape {tuple(precond.shape)}, expected {tuple(b.shape)}"
            )
        pinv = precond

        def apply_m(r: torch.Tensor) -> torch.Tensor:
            return pinv * r
    else:
        apply_m = precond

    check_finite(b, "right-hand side b")
    check_finite(x, "warm start x0")
    bnorm = _bdot(b, b).sqrt()
    bnorm = torch.where(bnorm > 0, bnorm, torch.ones_like(bnorm))
    if r0 is None:
        r = b - matvec(x)
    else:
        if r0.shape != b.shape:
            raise ShapeError(f"r0 has shape {tuple(r0.shape)} but b has shape {tuple(b.shape)}")
        r = r0.clone(memory_format=torch.contiguous_format)
        check_finite(r, "start residual r0")
    z = apply_m(r)
    p = z.clone()
    rz = _bdot(r, z)
    res = _bdot(r, r).sqrt() / bnorm
    active = res > tol
    reached = ~active
    broke = torch.zeros_like(active)
    iters = torch.zeros(b.shape[0], dtype=torch.long, device=b.device)
    it = 0
    while it < max_iter and bool(active.any()):
        ap = matvec(p)
        pap = _bdot(p, ap)
        ok = pap > 0
        alpha = torch.where(active & ok, rz / torch.where(ok, pap, 1), 0)
        x.addcmul_(_bview(alpha, x), p)  # x, r and p are private: update in place
        r.addcmul_(_bview(alpha, r), ap, value=-1)
        z = apply_m(r)
        rz_new = _bdot(r, z)
        beta = torch.where(active & (rz > 0), rz_new / torch.where(rz > 0, rz, 1), 0)
        p.mul_(_bview(beta, p)).add_(z)
        rz = rz_new
        res = _bdot(r, r).sqrt() / bnorm
        iters = iters + active.long()
        it += 1
        # breakdown (pap <= 0 or NaN): A is not SPD on this item; stop it, do not claim success
        broke = broke | (active & ~ok)
        done = active & ok & ~(res > tol)
        if bool(done.any()):
            # residual replacement: the recursive residual drifts in float32, so confirm
            # with the true one and restart the direction where it is not yet reached
            r_true = b - matvec(x)
            res_true = _bdot(r_true, r_true).sqrt() / bnorm
            redo = done & (res_true > tol)
            # the finished items keep their true residual (what PCGResult.r hands on)
            r = torch.where(_bview(done, r), r_true, r)
            if bool(redo.any()):
                rv = _bview(redo, r)
                z_true = apply_m(r)
                p = torch.where(rv, z_true, p)
                rz = torch.where(redo, _bdot(r, z_true), rz)
                res = torch.where(redo, res_true, res)
            reached = reached | (done & ~redo)
        active = active & ~reached & ~broke
    converged = bool(reached.all())
    if true_residual:
        # report the true residual (the recursive one drifts in float32)
        r = b - matvec(x)
        res = _bdot(r, r).sqrt() / bnorm
    if warn and not converged:
        why = " (breakdown: the operator is not positive definite)" if bool(broke.any()) else ""
        warnings.warn(
            f"PCG stopped after {it} iterations with relative residual "
            f"{float(res.max()):.3g} > tol {tol:g}{why}",
            ConvergenceWarning,
            stacklevel=2,
        )
    return PCGResult(
        x=x, iterations=it, residual=res, converged=converged, item_iterations=iters, r=r
    )
