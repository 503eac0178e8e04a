"""Row helpers that the numba kernels inline (:mod:`torchiid.priors.stencil_kernels`)."""

from __future__ import annotations

from typing import Any

import numpy.typing as npt
from numba import njit

__all__ = ["Array", "span", "zero_rows", "mask_row"]

#: a numpy array as the kernels take it (numba types them at the call)
Array = npt.NDArray[Any]


@njit(inline="always")
def span(dx: int, wd: int) -> tuple[int, int]:  # pragma: no cover - compiled
    """``(x0, n)``: the first column and the count of pixels ``i`` whose ``i + dx`` is inside."""
    x0 = max(0, -dx)
    return x0, min(wd, wd - dx) - x0


@njit(inline="always")
def zero_rows(out: Array, r0: int, r1: int) -> None:  # pragma: no cover - compiled
    """Zero rows ``r0 .. r1 − 1`` (of the batch's ``B·H``) of ``out`` ``(B, C, H, W)``."""
    h = out.shape[2]
    for r in range(r0, r1):
        b = r // h
        y = r - b * h
        for c in range(out.shape[1]):
            out[b, c, y, :] = 0.0


@njit(inline="always")
def mask_row(
    mask: Array, b: int, y: int, dy: int, dx: int, x0: int, n: int, o: Array, value: float
) -> None:  # pragma: no cover - compiled
    """Set ``o[t]`` to ``value`` where pair ``t`` of a run touches a pixel outside ``mask``.

    The run: the ``n`` pixels from ``(y, x0)`` of image ``b`` paired with ``(dy, dx)`` away.
    """
    mi = mask[b, 0, y, x0 : x0 + n]
    mj = mask[b, 0, y + dy, x0 + dx : x0 + dx + n]
    for t in range(n):
        if not (mi[t] and mj[t]):
            o[t] = value
