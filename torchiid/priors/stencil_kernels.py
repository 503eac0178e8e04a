"""The numba kernels behind :mod:`torchiid.priors.kernels` (imported only when numba is).

Each kernel computes the output rows ``r0 .. r1 - 1`` (over the batch's ``B·H`` rows) on the
calling thread, without the GIL, so :mod:`torchiid.priors.kernel_runtime` can run bands of rows
on several threads. The stencil product, called hundreds of times per image at well under a
millisecond, also comes as ``gather_parallel`` on numba's own thread pool (``prange``), whose
hand-off is cheaper than a Python thread pool's. Only multi-thread processes use it: its
compilation takes longer (first run only) and, in one-thread processes, its pool's idle
threads would spin against the other processes.

This module holds the stencil product and the colour affinity; the matting and Bregman
kernels live in :mod:`~torchiid.priors.matting_kernels` and
:mod:`~torchiid.priors.bregman_kernels` and are importable from here.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from torchiid.priors.bregman_kernels import add_halos, bregman_update
from torchiid.priors.kernel_rows import Array, mask_row, span
from torchiid.priors.matting_kernels import matting_weights, matting_windows

__all__ = [
    "gather",
    "gather_parallel",
    "matting_windows",
    "matting_weights",
    "affinity_exponent",
    "scale_by_factor",
    "bregman_update",
    "add_halos",
]


def _gather(  # pragma: no cover - compiled
    z: Array,
    w: Array,
    dys: Array,
    dxs: Array,
    out: Array,
    square: bool,
    degree: bool,
    r0: int,
    r1: int,
) -> Array:
    """``out_i = Σ_k w_k(i) (z_i − z_{i + o_k}) + Σ_k w_k(i − o_k) (z_i − z_{i − o_k})``.

    The weighted Laplacian product in difference form (see :mod:`torchiid.priors.kernels`);
    ``square``: the weights enter squared; ``degree``: ``out_i = Σ w`` instead, each pixel's
    summed pair weights (``z`` is then read for its shape only).
    """
    for r in range(r0, r1):
        _gather_row(z, w, dys, dxs, out, square, degree, r)
    return out


def _gather_all(  # pragma: no cover - compiled
    z: Array, w: Array, dys: Array, dxs: Array, out: Array, square: bool, degree: bool
) -> Array:
    """:func:`_gather` over all rows with numba's ``prange`` (its thread pool)."""
    for r in prange(z.shape[0] * z.shape[2]):
        _gather_row(z, w, dys, dxs, out, square, degree, r)
    return out


@njit(inline="always")
def _gather_row(  # pragma: no cover - compiled
    z: Array, w: Array, dys: Array, dxs: Array, out: Array, square: bool, degree: bool, r: int
) -> None:
    nc, h, wd = z.shape[1], z.shape[2], z.shape[3]
    nk = dys.shape[0]
    b = r // h
    y = r - b * h
    for c in range(nc):
        out[b, c, y, :] = 0.0
    for k in range(nk):
        dy = dys[k]
        dx = dxs[k]
        if y + dy < h:  # i = (y, x) with partner j = i + (dy, dx), weight at i
            x0, n = span(dx, wd)
            wr = w[b, k, y, x0 : x0 + n]
            for c in range(nc):
                zi = z[b, c, y, x0 : x0 + n]
                zj = z[b, c, y + dy, x0 + dx : x0 + dx + n]
                _accumulate(out[b, c, y, x0 : x0 + n], wr, zi, zj, n, square, degree)
        if y - dy >= 0:  # i = (y, x) as the partner of j = i − (dy, dx), weight at j
            x0, n = span(-dx, wd)
            wr = w[b, k, y - dy, x0 - dx : x0 - dx + n]
            for c in range(nc):
                zi = z[b, c, y, x0 : x0 + n]
                zj = z[b, c, y - dy, x0 - dx : x0 - dx + n]
                _accumulate(out[b, c, y, x0 : x0 + n], wr, zi, zj, n, square, degree)


@njit(inline="always")
def _accumulate(  # pragma: no cover - compiled
    a: Array, wr: Array, zi: Array, zj: Array, n: int, square: bool, degree: bool
) -> None:
    if degree:
        if square:
            for t in range(n):
                a[t] += wr[t] * wr[t]
        else:
            for t in range(n):
                a[t] += wr[t]
    elif square:
        for t in range(n):
            a[t] += wr[t] * wr[t] * (zi[t] - zj[t])
    else:
        for t in range(n):
            a[t] += wr[t] * (zi[t] - zj[t])


def _affinity_exponent(  # pragma: no cover - compiled
    feat: Array,
    mask: Array,
    dys: Array,
    dxs: Array,
    scale: float,
    floor: float,
    out: Array,
    r0: int,
    r1: int,
) -> Array:
    """``out_k(i) = scale · ‖f_i − f_j‖²``, ``j = i + o_k``: the exponent of the affinity.

    ``-inf`` (a weight of 0 once exponentiated) where the exponent is below ``floor`` (see
    ``affinity.MIN_EXPONENT``), where the pair leaves the image and, with ``mask``
    ``(B, 1, H, W)`` (``(0, 0, 0, 0)`` for none), where it touches a pixel outside. The caller
    exponentiates (torch's ``exp`` is vectorised, numba's is not without Intel's SVML).
    """
    nb, nd, h, wd = feat.shape
    nk = dys.shape[0]
    use_mask = mask.shape[0] > 0
    ninf = -np.inf
    for r in range(r0, r1):
        b = r // h
        y = r - b * h
        for k in range(nk):
            dy = dys[k]
            dx = dxs[k]
            orow = out[b, k, y]
            orow[:] = ninf
            if y + dy >= h:
                continue
            x0, n = span(dx, wd)
            o = orow[x0 : x0 + n]
            if nd == 3:  # colour features: one pass, the same sums in the same order
                fi0 = feat[b, 0, y, x0 : x0 + n]
                fj0 = feat[b, 0, y + dy, x0 + dx : x0 + dx + n]
                fi1 = feat[b, 1, y, x0 : x0 + n]
                fj1 = feat[b, 1, y + dy, x0 + dx : x0 + dx + n]
                fi2 = feat[b, 2, y, x0 : x0 + n]
                fj2 = feat[b, 2, y + dy, x0 + dx : x0 + dx + n]
                for t in range(n):
                    e0 = fi0[t] - fj0[t]
                    e1 = fi1[t] - fj1[t]
                    e2 = fi2[t] - fj2[t]
                    v = (e0 * e0 + e1 * e1 + e2 * e2) * scale
                    o[t] = v if v >= floor else ninf
            else:
                o[:] = 0.0
                for d in range(nd):  # squared feature distance of each pair
                    fi = feat[b, d, y, x0 : x0 + n]
                    fj = feat[b, d, y + dy, x0 + dx : x0 + dx + n]
                    for t in range(n):
                        e = fi[t] - fj[t]
                        o[t] += e * e
                for t in range(n):
                    v = o[t] * scale
                    o[t] = v if v >= floor else ninf
            if use_mask:
                mask_row(mask, b, y, dy, dx, x0, n, o, ninf)
    return out


def _scale_by_factor(  # pragma: no cover - compiled
    out: Array, sem: Array, a_l: float, a_m: float, r0: int, r1: int
) -> Array:
    """``out *= a_l + a_m · sem`` over the rows ``r0 .. r1 - 1`` of ``(B·K·H, W)`` views."""
    for r in range(r0, r1):
        o = out[r]
        s = sem[r]
        for t in range(o.shape[0]):
            o[t] *= a_l + a_m * s[t]
    return out


# the product keeps IEEE semantics (no reassociation of its sums)
gather = njit(nogil=True, cache=True, boundscheck=False)(_gather)
gather_parallel = njit(parallel=True, nogil=True, cache=True, boundscheck=False)(_gather_all)
# IEEE semantics: fast-math would let LLVM assume that no value is infinite, and the exponent
# marks the pairs without weight by -inf
affinity_exponent = njit(nogil=True, cache=True, boundscheck=False)(_affinity_exponent)
scale_by_factor = njit(nogil=True, cache=True, boundscheck=False)(_scale_by_factor)
