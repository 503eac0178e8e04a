"""Batched preconditioned conjugate gradient in torch (CPU or CUDA).

Solves ``A x = b`` for symmetric positive (semi-)definite ``A`` given only as a function
``matvec(x)``. The first dimension of ``b`` is the batch: each image has its own step sizes,
residual and stopping test, so a batch gives the same answer as its images one by one.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchiid.core.exceptions import ConvergenceWarning, ShapeError

__all__ = ["PCGResult", "pcg"]


@dataclass(frozen=True)
class PCGResult:
    """Result of :func:`pcg`.

    Attributes:
        x: the solution, shaped like ``b``.
        iterations: iterations run (the batch's maximum).
        residual: ``(B,)`` final relative residual ``||b - A x|| / ||b||`` per batch item.
        converged: whether every batch item reached the tolerance.
    """

    x: torch.Tensor
    iterations: int
    residual: torch.Tensor
    converged: bool


def _bdot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
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

    Returns:
        :class:`PCGResult`.
    """
    if b.dim() < 1 or b.shape[0] == 0:
        raise ShapeError(f"expected a batched right-hand side (B, ...), got {tuple(b.shape)}")
    x = torch.zeros_like(b) if x0 is None else x0.clone()
    if x.shape != b.shape:
        raise ShapeError(f"x0 has shape {tuple(x.shape)} but b has shape {tuple(b.shape)}")
    if precond is None:
        def apply_m(r: torch.Tensor) -> torch.Tensor:
            return r
    elif isinstance(precond, torch.Tensor):
        if precond.shape != b.shape:
            raise ShapeError(
                f"preconditioner has shape {tuple(precond.shape)}, expected {tuple(b.shape)}")
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
    active = res > tol
    it = 0
    while it < max_iter and bool(active.any()):
        ap = matvec(p)
        pap = _bdot(p, ap)
        alpha = torch.where(active & (pap > 0), rz / torch.where(pap > 0, pap, 1), 0)
        x = x + _bview(alpha, x) * p
        r = r - _bview(alpha, r) * ap
        z = apply_m(r)
        rz_new = _bdot(r, z)
        beta = torch.where(active & (rz > 0), rz_new / torch.where(rz > 0, rz, 1), 0)
        p = z + _bview(beta, p) * p
        rz = rz_new
        res = _bdot(r, r).sqrt() / bnorm
        active = active & (res > tol) & (pap > 0)
        it += 1
    converged = not bool(active.any())
    # report the true residual (the recursive one drifts in float32)
    r_true = b - matvec(x)
    res = _bdot(r_true, r_true).sqrt() / bnorm
    if warn and not converged:
        warnings.warn(
            f"PCG stopped after {it} iterations with relative residual "
            f"{float(res.max()):.3g} > tol {tol:g}",
            ConvergenceWarning,
            stacklevel=2,
        )
    return PCGResult(x=x, iterations=it, residual=res, converged=converged)
