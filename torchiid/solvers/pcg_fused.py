"""The PCG iteration of :func:`~torchiid.solvers.pcg.pcg` as fused passes, on the CPU.

Besides the operator's product, an iteration makes about a dozen passes over vectors shaped
like the right-hand side (``pᵀAp``, the updates of ``x`` and ``r``, ``z = M⁻¹ r``, ``rᵀz``,
``rᵀr``, the new direction) and some forty operations on the ``(B,)`` step sizes, masks and
residuals. On a 512×341 image each of those takes microseconds, dispatch included; as torch
ops they cost more than the vector passes themselves (the documentation's Method page, "The
PCG iteration on the CPU"). Where the compiled kernels apply
(CPU float tensors, no autograd, a Jacobi preconditioner or none: :func:`applies`), this
iteration makes three compiled passes (:mod:`torchiid.solvers.pcg_kernels`): ``pᵀAp``; ``x``,
``r``, ``rᵀz`` and ``rᵀr``; ``p = z + βp``, with ``z`` computed on the fly instead of
stored, and keeps the per-item scalars in numpy. The iteration is the same as the torch ops'
(per-item step sizes, stops and breakdown, the true-residual check), with the dot products
summed in float64 in fixed chunks: the same values up to rounding, whatever the thread count.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import cache
from types import ModuleType

import numpy as np
import torch

from torchiid.core.check import check_shape
from torchiid.priors.kernel_runtime import compiled, parallel_lock, usable

__all__ = ["applies", "iterate", "PRODUCT"]

#: what a shape error calls the operator's output
PRODUCT = "the operator's output matvec(x) (shaped like its input x)"

logger = logging.getLogger(__name__)

#: ``x -> A x`` on a batch shaped like the right-hand side
Operator = Callable[[torch.Tensor], torch.Tensor]


@cache
def _kernels() -> tuple[ModuleType, ModuleType] | None:
    """``(numba, the kernel module)``, or ``None`` where the compiled kernels are off."""
    found = compiled()
    if found is None:
        return None
    try:
        from torchiid.solvers import pcg_kernels
    except Exception as exc:  # pragma: no cover - e.g. no writable directory for numba's cache
        logger.warning("compiled PCG kernels unavailable (%s); using the torch ops", exc)
        return None
    return found[0], pcg_kernels


def applies(precond: object, b: torch.Tensor, x: torch.Tensor, r: torch.Tensor) -> bool:
    """Whether :func:`iterate` runs this solve.

    It does for a non-empty batch of CPU float ``b``, ``x`` and start residual ``r`` of one
    dtype (no autograd: ``r`` carries the operator's), with the compiled kernels on and a
    Jacobi preconditioner (a tensor shaped like ``b``) or none.
    """
    if precond is not None and not isinstance(precond, torch.Tensor):
        return False
    if b.dim() < 1 or b.shape[0] == 0 or not usable(b, x, r) or _kernels() is None:
        return False
    return precond is None or usable(b, precond)


def _rows(t: torch.Tensor) -> np.ndarray:
    return t.view(t.shape[0], -1).numpy()


class _Passes:
    """The three compiled passes over one solve's ``(B, N)`` vectors."""

    def __init__(self, minv: torch.Tensor | None, like: torch.Tensor) -> None:
        found = _kernels()
        assert found is not None
        self._numba, self._k = found
        self.dtype = like.numpy().dtype
        nb = like.shape[0]
        self._nc = self._k.chunks(like[0].numel())
        self.minv = None if minv is None else minv.contiguous()
        self._m = np.zeros((0, 0), self.dtype) if self.minv is None else _rows(self.minv)
        threads = min(torch.get_num_threads(), self._numba.config.NUMBA_NUM_THREADS)
        # handing chunks to the pool costs more than it saves below two per thread
        self._threads = threads if nb * self._nc >= 2 * threads else 1

    def _run(self, name: str, *args: np.ndarray) -> None:
        if self._threads <= 1:
            getattr(self._k, name)(*args)
            return
        with parallel_lock:  # numba's workqueue layer takes one caller at a time
            self._numba.set_num_threads(self._threads)
            getattr(self._k, name + "_parallel")(*args)

    def precondition(self, r: torch.Tensor) -> torch.Tensor:
        return r.clone() if self.minv is None else self.minv * r

    def dot(self, a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
        parts = np.empty((a.shape[0], self._nc))
        self._run("dots", _rows(a.contiguous()), _rows(b.contiguous()), parts)
        out: np.ndarray = parts.sum(axis=1)
        return out

    def update(
        self,
        x: torch.Tensor,
        r: torch.Tensor,
        p: torch.Tensor,
        ap: torch.Tensor,
        alpha: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        sums = np.empty((2, x.shape[0], self._nc))
        ap = ap.contiguous()
        self._run("update", _rows(x), _rows(r), _rows(p), _rows(ap), self._m,
                  alpha.astype(self.dtype), sums)  # fmt: skip
        totals: np.ndarray = sums.sum(axis=2)
        return totals[0], totals[1]

    def direction(self, p: torch.Tensor, r: torch.Tensor, beta: np.ndarray) -> None:
        self._run("direction", _rows(p), _rows(r), self._m, beta.astype(self.dtype))


def _ratio(num: np.ndarray, den: np.ndarray, use: np.ndarray) -> np.ndarray:
    """``num / den`` where ``use``, else 0."""
    return np.where(use, num / np.where(use, den, 1.0), 0.0)


def iterate(
    matvec: Operator,
    b: torch.Tensor,
    x: torch.Tensor,
    r: torch.Tensor,
    minv: torch.Tensor | None,
    limits: tuple[float, int],
    observe: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], None] | None = None,
) -> tuple[tuple[torch.Tensor, ...], int]:
    """The PCG iteration from ``x`` with residual ``r`` (contiguous; updated in place).

    ``limits``: the relative tolerance and the iteration cap; ``observe(x, res, active)``,
    if given, is called after every iteration with the recursive relative residuals and the
    items that were active in it. Returns ``((r, bnorm, res, reached, broke, iters), it)``:
    the per-item state as tensors and the iterations run, what
    :func:`~torchiid.solvers.pcg.pcg`'s run holds.
    """
    tol, max_iter = limits
    ops = _Passes(minv, b)
    bnorm = np.sqrt(ops.dot(b, b))
    bnorm = np.where(bnorm > 0, bnorm, 1.0)
    z = ops.precondition(r)
    p = z.contiguous()
    rz = ops.dot(r, z)
    res = np.sqrt(ops.dot(r, r)) / bnorm
    active = res > tol
    reached, broke = ~active, np.zeros_like(active)
    iters = np.zeros(b.shape[0], dtype=np.int64)
    it = 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        while it < max_iter and active.any():
            ap = matvec(p)
            check_shape(ap, tuple(p.shape), PRODUCT)  # the kernels index both alike
            ap = ap.to(p.dtype)
            pap = ops.dot(p, ap)
            ok = pap > 0
            rz_new, rr = ops.update(x, r, p, ap, _ratio(rz, pap, active & ok))
            ops.direction(p, r, _ratio(rz_new, rz, active & (rz > 0)))
            rz = rz_new
            res = np.sqrt(rr) / bnorm
            iters += active
            it += 1
            if observe is not None:
                observe(x, torch.from_numpy(res).to(b.dtype), torch.from_numpy(active.copy()))
            # breakdown (pap <= 0 or NaN): A is not SPD on this item; stop it
            broke |= active & ~ok
            done = active & ok & ~(res > tol)
            if done.any():
                # residual replacement, as in the torch iteration
                r_true = b - matvec(x)
                res_true = np.sqrt(ops.dot(r_true, r_true)) / bnorm
                redo = done & (res_true > tol)
                r[torch.from_numpy(done)] = r_true[torch.from_numpy(done)]
                if redo.any():
                    z_true = ops.precondition(r)
                    p[torch.from_numpy(redo)] = z_true[torch.from_numpy(redo)]
                    rz = np.where(redo, ops.dot(r, z_true), rz)
                    res = np.where(redo, res_true, res)
                reached |= done & ~redo
            active &= ~reached & ~broke
    dtype = b.dtype
    state = (
        r,
        torch.from_numpy(bnorm).to(dtype),
        torch.from_numpy(res).to(dtype),
        torch.from_numpy(reached),
        torch.from_numpy(broke),
        torch.from_numpy(iters),
    )
    return state, it
