"""The numba kernels of ``StencilL1Term``'s Bregman update (:mod:`torchiid.priors.bregman_pass`).

One pass over the pairs updates every Bregman variable, writes it back (or not) and scatters
the update's contribution to the next ``z`` step's right-hand side; the measured mode also
sums what the duality gap needs. IEEE semantics (no fast-math): the variable is the one the
torch ops would store.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from torchiid.priors.kernel_rows import Array, span, zero_rows

__all__ = ["bregman_update", "add_halos"]


def _bregman_update(
    zs: Array,
    w: Array,
    offsets: tuple[Array, Array],
    state: Array,
    mode: tuple[float, bool, bool, float, float],
    out: tuple[Array, Array],
    measured: tuple[Array, Array, Array],
    block: int,
    k0: int,
    k1: int,
) -> Array:  # pragma: no cover - compiled
    """A Split-Bregman update of ``StencilL1Term``: the new state and the right-hand side.

    Arguments packed by role: ``offsets = (dys, dxs)``; ``mode = (lam, read, write, scale_in,
    inv_out)``; ``out = (rhs, halo)``; ``measured = (adj, halo2, stats)``.

    ``zs`` ``(m + 1, B, C, H, W)``: the ``z`` of ``m`` earlier updates to replay, then the
    current one. For every pair ``(i, j = i + o_k)`` and channel the Bregman variable ``b``
    starts from ``state`` ``(B, C, K, H, W)`` (``read``) or from 0, goes through the replayed
    updates ``b ← clamp(b + w (z_i − z_j), −λ, λ)`` (none when ``m = 0``), then ``u = b + w (z_i
    − z_j)``, ``b' = clamp(u, −λ, λ)`` is written back to ``state`` (``write``), and ``w (u −
    2b')`` (``w (d − b')``) is added to ``rhs_i`` and subtracted from ``rhs_j``. These are the
    torch path's operations in its order, so ``b'`` is the value that path stores. With
    ``write=False`` and a history no ``(B, C, K, H, W)`` variable is read or written at all.

    A 16-bit fixed-point ``state`` (``int16``; ``inv_out > 0``) holds ``b`` as ``q`` with ``b =
    q · scale_in`` when read, and is written as ``q' = rint(b' · inv_out)`` (round half to
    even, as ``torch.round``); the right-hand side uses the unrounded ``b'``. A float ``state``
    is read and written as it is (``inv_out = 0``; ``scale_in`` unused).

    Measured update (``stats`` ``(blocks, B, 4)`` float64, not empty): the same state and
    right-hand side, and also ``w b'`` added to ``adj_i`` and subtracted from ``adj_j`` (``adj
    = (W M)ᵀ b'``, rows after the block into ``halo2[blk]``), and per block and image the sums
    ``Σ |w (z_i − z_j)|``, ``Σ (b' − b)²`` (the primal residual ``W M z − d``), ``Σ (w (z_i −
    z_j))²`` and ``Σ d²`` into ``stats[blk, b]``: for the duality gap and residual balancing of
    :func:`torchiid.solvers.split_bregman.split_bregman`. They run per column in the arrays'
    dtype over a row's pairs (so the loops vectorise), then per row in float64. Otherwise
    ``adj``, ``halo2`` and ``stats`` are empty and untouched.

    The ``B·H`` rows are cut into blocks of ``block`` rows; this call does blocks ``k0 .. k1 −
    1``. Each block zeroes and writes its own rows; its contributions to the rows after it go
    to ``halo[blk]`` ``(D, C, W)`` (``D`` the largest ``dy``; row ``end + t`` at ``halo[blk,
    t]``, zeroed here), which :func:`_add_halos` adds afterwards. The blocks do not depend on
    the number of threads, so neither does the result. ``lam`` must have the arrays' dtype (a
    float64 scalar would turn the float32 sums into float64 ones).
    """
    dys, dxs = offsets
    lam, read, write, scale_in, inv_out = mode
    rhs, halo = out
    adj, halo2, stats = measured
    m = zs.shape[0] - 1
    nb, nc, h, wd = zs.shape[1], zs.shape[2], zs.shape[3], zs.shape[4]
    rows = nb * h
    nk = dys.shape[0]
    bbuf = np.empty(wd, dtype=zs.dtype)  # a row of Bregman variables
    quant = inv_out > 0
    measure = stats.shape[0] > 0
    cbuf = np.empty(wd if measure else 0, dtype=zs.dtype)  # w b', for adj
    nbuf = np.empty(wd if measure else 0, dtype=zs.dtype)  # b', to store
    acc = np.zeros((4, wd if measure else 0), dtype=zs.dtype)  # per-column sums of a row
    for blk in range(k0, k1):
        r0 = blk * block
        r1 = min(rows, r0 + block)
        halo[blk] = 0.0
        zero_rows(rhs, r0, r1)
        if measure:
            halo2[blk] = 0.0
            stats[blk] = 0.0
            zero_rows(adj, r0, r1)
        for r in range(r0, r1):
            b = r // h
            y = r - b * h
            a1, a2, a3, a4 = acc[0], acc[1], acc[2], acc[3]
            for k in range(nk):
                dy = dys[k]
                dx = dxs[k]
                if y + dy >= h:
                    continue
                x0, n = span(dx, wd)
                wr = w[b, k, y, x0 : x0 + n]
                rj = r + dy
                for c in range(nc):
                    pos = (b, c, y, dy, x0, dx, rj - r1)  # rj >= r1: j's row is past the block
                    oi, oj = _pair_runs(rhs, halo[blk], pos, n)
                    bb = bbuf[:n]
                    if read:
                        _decode(state[b, c, k, y, x0 : x0 + n], bb, quant, scale_in)
                    else:
                        bb[:] = 0.0
                    for s in range(m):
                        zi = zs[s, b, c, y, x0 : x0 + n]
                        zj = zs[s, b, c, y + dy, x0 + dx : x0 + dx + n]
                        for t in range(n):
                            u = (zi[t] - zj[t]) * wr[t] + bb[t]
                            bb[t] = min(max(u, -lam), lam)
                    zi = zs[m, b, c, y, x0 : x0 + n]
                    zj = zs[m, b, c, y + dy, x0 + dx : x0 + dx + n]
                    if measure:
                        nw = nbuf[:n]
                        _measured_pairs(zi, zj, wr, bb, cbuf[:n], nw, a1, a2, a3, a4, lam)
                        if write and quant:
                            sr = state[b, c, k, y, x0 : x0 + n]
                            for t in range(n):
                                sr[t] = np.rint(nw[t] * inv_out)
                        elif write:
                            sr = state[b, c, k, y, x0 : x0 + n]
                            sr[:] = nw
                        ai, aj = _pair_runs(adj, halo2[blk], pos, n)
                        cb = cbuf[:n]
                        for t in range(n):
                            ai[t] += cb[t]
                        for t in range(n):
                            aj[t] -= cb[t]
                    elif write and quant:
                        sr = state[b, c, k, y, x0 : x0 + n]
                        for t in range(n):
                            wt = wr[t]
                            u = (zi[t] - zj[t]) * wt + bb[t]
                            bn = min(max(u, -lam), lam)
                            sr[t] = np.rint(bn * inv_out)
                            bb[t] = (u - (bn + bn)) * wt
                    elif write:
                        sr = state[b, c, k, y, x0 : x0 + n]
                        for t in range(n):  # bb becomes w (d − b'), the pair's contribution
                            wt = wr[t]
                            u = (zi[t] - zj[t]) * wt + bb[t]
                            bn = min(max(u, -lam), lam)
                            sr[t] = bn
                            bb[t] = (u - (bn + bn)) * wt  # bn + bn is exact: one rounding
                    else:
                        for t in range(n):
                            wt = wr[t]
                            u = (zi[t] - zj[t]) * wt + bb[t]
                            bn = min(max(u, -lam), lam)
                            bb[t] = (u - (bn + bn)) * wt
                    # separate loops: oi and oj may overlap (dy = 0), each still vectorises
                    for t in range(n):
                        oi[t] += bb[t]
                    for t in range(n):
                        oj[t] -= bb[t]
            if measure:
                for q in range(4):
                    total = 0.0
                    for t in range(wd):
                        total += acc[q, t]
                    stats[blk, b, q] += total
                acc[:] = 0.0
    return rhs


@njit(inline="always")
def _measured_pairs(  # pragma: no cover - compiled
    zi: Array,
    zj: Array,
    wr: Array,
    bb: Array,
    cb: Array,
    nw: Array,
    a1: Array,
    a2: Array,
    a3: Array,
    a4: Array,
    lam: float,
) -> None:
    """The update of a run of pairs in :func:`_bregman_update`'s measured mode.

    Leaves ``w (d − b')`` in ``bb`` (as the plain update), ``w b'`` in ``cb`` and ``b'`` in
    ``nw`` (to store), and adds the four measured quantities to the per-column sums ``a1`` ..
    ``a4`` (the rows of :func:`_bregman_update`'s ``acc``).
    """
    for t in range(bb.shape[0]):
        wt = wr[t]
        a = (zi[t] - zj[t]) * wt
        u = a + bb[t]
        bn = min(max(u, -lam), lam)
        a1[t] += abs(a)
        e = bn - bb[t]
        a2[t] += e * e
        a3[t] += a * a
        e = u - bn
        a4[t] += e * e
        nw[t] = bn
        cb[t] = bn * wt
        bb[t] = (u - (bn + bn)) * wt


def _add_halos(rhs: Array, halo: Array, block: int) -> Array:  # pragma: no cover - compiled
    """Add each block's ``halo`` (:func:`_bregman_update`) to the rows after it, in order."""
    nb, _, h, _ = rhs.shape
    rows = nb * h
    for blk in range(halo.shape[0]):
        end = min(rows, (blk + 1) * block)
        for t in range(halo.shape[1]):
            r = end + t
            if r >= rows:
                break
            b = r // h
            y = r - b * h
            rhs[b, :, y, :] += halo[blk, t]
    return rhs


@njit(inline="always")
def _pair_runs(
    out: Array, spill: Array, pos: tuple[int, int, int, int, int, int, int], n: int
) -> tuple[Array, Array]:  # pragma: no cover - compiled
    """The runs of ``n`` pairs' first and second pixels in ``out`` ``(B, C, H, W)``.

    ``pos = (b, c, y, dy, x0, dx, past)``: the run starts at ``(y, x0)`` of image ``b``,
    channel ``c``; its partners are ``(dy, dx)`` away. ``past >= 0``: the partners' row lies
    ``past`` rows after the block, in its halo ``spill`` ``(D, C, W)``.
    """
    b, c, y, dy, x0, dx, past = pos
    first = out[b, c, y, x0 : x0 + n]
    if past < 0:
        return first, out[b, c, y + dy, x0 + dx : x0 + dx + n]
    return first, spill[past, c, x0 + dx : x0 + dx + n]


@njit(inline="always")
def _decode(src: Array, bb: Array, quant: bool, scale_in: float) -> None:  # pragma: no cover
    """A run of stored Bregman variables into ``bb`` (decoded when fixed point)."""
    if quant:
        for t in range(bb.shape[0]):
            bb[t] = src[t] * scale_in
    else:
        bb[:] = src


bregman_update = njit(nogil=True, cache=True, boundscheck=False)(_bregman_update)
add_halos = njit(nogil=True, cache=True, boundscheck=False)(_add_halos)
