"""The numba kernels behind :mod:`torchiid.solvers.pcg_fused` (imported only when numba is).

Every array is a batch viewed as ``(B, N)`` rows. The work is cut into chunks of
:data:`CHUNK` elements of one row; each chunk's sums are accumulated in float64 and written
to its own slot of a ``(B, chunks)`` array, which the caller sums. The chunks, their order
and so the sums do not depend on the number of threads. Each kernel comes twice: on the
calling thread, and on numba's thread pool (``*_parallel``, ``prange`` over the chunks).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from numba import njit, prange

__all__ = [
    "CHUNK",
    "chunks",
    "dots",
    "dots_parallel",
    "update",
    "update_parallel",
    "direction",
    "direction_parallel",
]

Array = npt.NDArray[Any]

#: elements per chunk (16 KB of float32): long enough to amortise a chunk, short enough to
#: share a 512×341 image between two threads
CHUNK = 4096

# the float64 sums may be reordered (that vectorises them); nothing else is relaxed
_FAST = {"reassoc"}


def chunks(n: int) -> int:
    """How many chunks a row of ``n`` elements has."""
    return max(1, -(-n // CHUNK))


@njit(inline="always")
def _bounds(k: int, nc: int, n: int) -> tuple[int, int, int]:  # pragma: no cover - compiled
    """Row ``i`` and the element range ``lo .. hi − 1`` of chunk ``k`` (``nc`` per row)."""
    i = k // nc
    lo = (k - i * nc) * CHUNK
    return i, lo, min(n, lo + CHUNK)


@njit(inline="always")
def _dots_chunk(a: Array, b: Array, out: Array, k: int) -> None:  # pragma: no cover
    nc = out.shape[1]
    i, lo, hi = _bounds(k, nc, a.shape[1])
    ai, bi = a[i, lo:hi], b[i, lo:hi]  # 1-D runs: the loop vectorises
    acc = 0.0
    for t in range(hi - lo):
        acc += np.float64(ai[t]) * np.float64(bi[t])
    out[i, k - i * nc] = acc


@njit(inline="always")
def _update_chunk(  # pragma: no cover - compiled
    x: Array, r: Array, p: Array, ap: Array, minv: Array, alpha: Array, sums: Array, k: int
) -> None:
    nc = sums.shape[2]
    i, lo, hi = _bounds(k, nc, x.shape[1])
    a = alpha[i]
    xi, ri, pi, api = x[i, lo:hi], r[i, lo:hi], p[i, lo:hi], ap[i, lo:hi]
    s_rz = 0.0
    s_rr = 0.0
    if minv.shape[0] > 0:
        mi = minv[i, lo:hi]
        for t in range(hi - lo):
            xi[t] += a * pi[t]
            rv = ri[t] - a * api[t]
            ri[t] = rv
            s_rz += np.float64(rv) * np.float64(mi[t] * rv)
            s_rr += np.float64(rv) * np.float64(rv)
    else:
        for t in range(hi - lo):
            xi[t] += a * pi[t]
            rv = ri[t] - a * api[t]
            ri[t] = rv
            s_rr += np.float64(rv) * np.float64(rv)
        s_rz = s_rr
    sums[0, i, k - i * nc] = s_rz
    sums[1, i, k - i * nc] = s_rr


@njit(inline="always")
def _direction_chunk(  # pragma: no cover - compiled
    p: Array, r: Array, minv: Array, beta: Array, nc: int, k: int
) -> None:
    i, lo, hi = _bounds(k, nc, p.shape[1])
    bt = beta[i]
    pi, ri = p[i, lo:hi], r[i, lo:hi]
    if minv.shape[0] > 0:
        mi = minv[i, lo:hi]
        for t in range(hi - lo):
            pi[t] = mi[t] * ri[t] + bt * pi[t]
    else:
        for t in range(hi - lo):
            pi[t] = ri[t] + bt * pi[t]


def _dots(a: Array, b: Array, out: Array) -> None:  # pragma: no cover - compiled
    """``out[i, c] = Σ a[i, t] b[i, t]`` over chunk ``c`` of row ``i``, in float64."""
    for k in range(out.shape[0] * out.shape[1]):
        _dots_chunk(a, b, out, k)


def _dots_all(a: Array, b: Array, out: Array) -> None:  # pragma: no cover - compiled
    """:func:`_dots` on numba's pool."""
    for k in prange(out.shape[0] * out.shape[1]):
        _dots_chunk(a, b, out, k)


def _update(  # pragma: no cover - compiled
    x: Array, r: Array, p: Array, ap: Array, minv: Array, alpha: Array, sums: Array
) -> None:
    """``x += α p``, ``r −= α Ap`` (``α`` per row); per chunk ``rᵀ M⁻¹ r`` and ``rᵀ r``.

    ``minv``: the inverse diagonal ``(B, N)``, or a ``(0, 0)`` array for none; ``sums``:
    ``(2, B, chunks)`` float64, the two sums of every chunk.
    """
    for k in range(sums.shape[1] * sums.shape[2]):
        _update_chunk(x, r, p, ap, minv, alpha, sums, k)


def _update_all(  # pragma: no cover - compiled
    x: Array, r: Array, p: Array, ap: Array, minv: Array, alpha: Array, sums: Array
) -> None:
    """:func:`_update` on numba's pool."""
    for k in prange(sums.shape[1] * sums.shape[2]):
        _update_chunk(x, r, p, ap, minv, alpha, sums, k)


def _direction(p: Array, r: Array, minv: Array, beta: Array) -> None:  # pragma: no cover
    """``p = M⁻¹ r + β p`` (``β`` per row; ``minv`` as in :func:`_update`)."""
    nc = max(1, (p.shape[1] + CHUNK - 1) // CHUNK)
    for k in range(p.shape[0] * nc):
        _direction_chunk(p, r, minv, beta, nc, k)


def _direction_all(p: Array, r: Array, minv: Array, beta: Array) -> None:  # pragma: no cover
    """:func:`_direction` on numba's pool."""
    nc = max(1, (p.shape[1] + CHUNK - 1) // CHUNK)
    for k in prange(p.shape[0] * nc):
        _direction_chunk(p, r, minv, beta, nc, k)


def _jit(fn: Any, parallel: bool = False, fast: bool = False) -> Any:
    fastmath = _FAST if fast else False
    return njit(parallel=parallel, nogil=True, cache=True, boundscheck=False, fastmath=fastmath)(fn)


# the inlined chunk bodies take the flags of the kernel they are compiled into
dots = _jit(_dots, fast=True)
dots_parallel = _jit(_dots_all, parallel=True, fast=True)
update = _jit(_update, fast=True)
update_parallel = _jit(_update_all, parallel=True, fast=True)
direction = _jit(_direction)
direction_parallel = _jit(_direction_all, parallel=True)
