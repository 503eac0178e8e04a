"""The numba kernels behind :mod:`torchiid.priors.kernels` (imported only when numba is).

Each kernel computes the output rows ``r0 .. r1 - 1`` (over the batch's ``B·H`` rows) on the
calling thread, without the GIL, so :mod:`torchiid.priors.kernels` can run bands of rows on
several threads. The stencil product, called hundreds of times per image at well under a
millisecond, also comes as ``gather_parallel`` on numba's own thread pool (``prange``), whose
hand-off is cheaper than a Python thread pool's (measured at 512×384 on 2 threads, the
shading product: 0.33 ms against 0.74 ms). Only multi-thread processes use it: its
compilation takes about 3× longer (first run only) and, in one-thread processes, its pool's
idle threads spin against the other processes (measured: two one-thread pytest workers ran
3.4× slower with it).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

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


def _gather(z, w, dys, dxs, out, square, degree, r0, r1):  # pragma: no cover - compiled
    """``out_i = Σ_k w_k(i) (z_i − z_{i + o_k}) + Σ_k w_k(i − o_k) (z_i − z_{i − o_k})``.

    The weighted Laplacian product in difference form (see :mod:`torchiid.priors.kernels`);
    ``square``: the weights enter squared; ``degree``: ``out_i = Σ w`` instead, each pixel's
    summed pair weights (``z`` is then read for its shape only).
    """
    for r in range(r0, r1):
        _gather_row(z, w, dys, dxs, out, square, degree, r)
    return out


def _gather_all(z, w, dys, dxs, out, square, degree):  # pragma: no cover - compiled
    """:func:`_gather` over all rows with numba's ``prange`` (its thread pool)."""
    for r in prange(z.shape[0] * z.shape[2]):
        _gather_row(z, w, dys, dxs, out, square, degree, r)
    return out


@njit(inline="always")
def _gather_row(z, w, dys, dxs, out, square, degree, r):  # pragma: no cover - compiled
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
            x0, n = _span(dx, wd)
            wr = w[b, k, y, x0 : x0 + n]
            for c in range(nc):
                zi = z[b, c, y, x0 : x0 + n]
                zj = z[b, c, y + dy, x0 + dx : x0 + dx + n]
                _accumulate(out[b, c, y, x0 : x0 + n], wr, zi, zj, n, square, degree)
        if y - dy >= 0:  # i = (y, x) as the partner of j = i − (dy, dx), weight at j
            x0, n = _span(-dx, wd)
            wr = w[b, k, y - dy, x0 - dx : x0 - dx + n]
            for c in range(nc):
                zi = z[b, c, y, x0 : x0 + n]
                zj = z[b, c, y - dy, x0 - dx : x0 - dx + n]
                _accumulate(out[b, c, y, x0 : x0 + n], wr, zi, zj, n, square, degree)


@njit(inline="always")
def _accumulate(a, wr, zi, zj, n, square, degree):  # pragma: no cover - compiled
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


def _matting_weights(qp, img, dys, dxs, out, r0, r1):  # pragma: no cover - compiled
    """Pair weights of the matting Laplacian's 5×5 stencil (see ``MattingQuadratic.as_stencil``).

    ``qp`` ``(B, 11, H + 2, W + 2)``: the window sums' summands ``v_k·(D_k [6 symmetric
    entries], D_k μ_k, μ_kᵀ D_k μ_k, 1)``, window ``(wy, wx)`` at ``(wy + 2, wx + 2)`` and 0
    around; ``img`` ``(B, 3, H, W)``; ``out`` ``(B, K, H, W)`` (pairs leaving the image get 0).
    """
    nb, _, h, wd = img.shape
    nk = dys.shape[0]
    wp = qp.shape[3]
    sr = np.empty((11, wd))  # a row's window sums
    vs = np.empty((3, 11, wp))  # vertical sums of the window summands
    for r in range(r0, r1):
        b = r // h
        y = r - b * h
        # vs[d]: over padded rows y + d .. y + 2
        for c in range(11):
            r2 = qp[b, c, y + 2]
            r1_ = qp[b, c, y + 1]
            r0_ = qp[b, c, y]
            for x in range(wp):
                v = r2[x]
                vs[2, c, x] = v
                v = v + r1_[x]
                vs[1, c, x] = v
                vs[0, c, x] = v + r0_[x]
        for k in range(nk):
            dy = dys[k]
            dx = dxs[k]
            orow = out[b, k, y]
            orow[:] = 0.0
            if y + dy >= h:
                continue
            x0, n = _span(dx, wd)
            # windows holding i = (y, x) and j = i + (dy, dx): padded rows y + dy .. y + 2,
            # padded columns max(x, x + dx) .. min(x, x + dx) + 2
            lo = x0 + max(0, dx)
            ncol = 3 - abs(dx)
            for c in range(11):
                acc = sr[c, :n]
                acc[:] = 0.0
                for t in range(ncol):
                    row = vs[dy, c, lo + t : lo + t + n]
                    for x in range(n):
                        acc[x] += row[x]
            ii = img[b, :, y, x0 : x0 + n]
            jj = img[b, :, y + dy, x0 + dx : x0 + dx + n]
            o = orow[x0 : x0 + n]
            for x in range(n):
                i0 = ii[0, x]
                i1 = ii[1, x]
                i2 = ii[2, x]
                j0 = jj[0, x]
                j1 = jj[1, x]
                j2 = jj[2, x]
                quad = sr[0, x] * i0 * j0 + sr[1, x] * i1 * j1 + sr[2, x] * i2 * j2
                quad += sr[3, x] * (i0 * j1 + i1 * j0)
                quad += sr[4, x] * (i0 * j2 + i2 * j0)
                quad += sr[5, x] * (i1 * j2 + i2 * j1)
                lin = sr[6, x] * (i0 + j0) + sr[7, x] * (i1 + j1) + sr[8, x] * (i2 + j2)
                o[x] = (sr[10, x] + quad - lin + sr[9, x]) / 9.0
    return out


def _matting_windows(img, mask, eps, qp, r0, r1):  # pragma: no cover - compiled
    """The per-window summands of :func:`_matting_weights`, for window rows ``r0 .. r1 - 1``.

    ``img`` ``(B, 3, H, W)`` float64, the centred base image; ``mask`` ``(B, 1, H, W)`` bool
    (or ``(0, 0, 0, 0)``: none; a window with a pixel outside it is dropped); ``eps``: Levin's
    regulariser. Writes ``qp[b, :, wy + 2, wx + 2] = v·(D [6 symmetric entries], D μ,
    μᵀ D μ, 1)`` for the ``(B·(H − 2))`` window rows, where ``μ`` and ``Σ`` are the window's
    mean and covariance, ``D = (Σ + ε/9 U)⁻¹`` by the ``L D Lᵀ`` closed form of
    ``matting._inv_sym3`` and ``v`` 1 for a kept window, 0 for a dropped one. ``qp``'s first
    two and last two rows are left to the caller (zeros); its first two and last two columns
    are zeroed here, in the rows of these windows.
    """
    nb, _, h, wd = img.shape
    hw = h - 2
    use_mask = mask.shape[0] > 0
    for r in range(r0, r1):
        b = r // hw
        wy = r - b * hw
        for c in range(11):
            qp[b, c, wy + 2, 0] = 0.0
            qp[b, c, wy + 2, 1] = 0.0
            qp[b, c, wy + 2, wd] = 0.0
            qp[b, c, wy + 2, wd + 1] = 0.0
        for wx in range(wd - 2):
            s0 = s1 = s2 = 0.0
            s00 = s11 = s22 = s01 = s02 = s12 = 0.0
            inside = True
            for yy in range(wy, wy + 3):
                for xx in range(wx, wx + 3):
                    a0 = img[b, 0, yy, xx]
                    a1 = img[b, 1, yy, xx]
                    a2 = img[b, 2, yy, xx]
                    s0 += a0
                    s1 += a1
                    s2 += a2
                    s00 += a0 * a0
                    s11 += a1 * a1
                    s22 += a2 * a2
                    s01 += a0 * a1
                    s02 += a0 * a2
                    s12 += a1 * a2
                    if use_mask and not mask[b, 0, yy, xx]:
                        inside = False
            py = wy + 2
            px = wx + 2
            if not inside:
                for c in range(11):
                    qp[b, c, py, px] = 0.0
                continue
            m0 = s0 / 9.0
            m1 = s1 / 9.0
            m2 = s2 / 9.0
            ca = s00 / 9.0 - m0 * m0 + eps / 9.0
            cb = s01 / 9.0 - m0 * m1
            cc = s02 / 9.0 - m0 * m2
            cd = s11 / 9.0 - m1 * m1 + eps / 9.0
            ce = s12 / 9.0 - m1 * m2
            cf = s22 / 9.0 - m2 * m2 + eps / 9.0
            l21 = cb / ca
            l31 = cc / ca
            d2 = cd - l21 * cb
            l32 = (ce - l31 * cb) / d2
            d3 = cf - l31 * cc - l32 * l32 * d2
            mm = l21 * l32 - l31
            q1 = 1.0 / ca
            q2 = 1.0 / d2
            q3 = 1.0 / d3
            i00 = q1 + l21 * l21 * q2 + mm * mm * q3
            i01 = -l21 * q2 - mm * l32 * q3
            i02 = mm * q3
            i11 = q2 + l32 * l32 * q3
            i12 = -l32 * q3
            i22 = q3
            dm0 = i00 * m0 + i01 * m1 + i02 * m2
            dm1 = i01 * m0 + i11 * m1 + i12 * m2
            dm2 = i02 * m0 + i12 * m1 + i22 * m2
            qp[b, 0, py, px] = i00
            qp[b, 1, py, px] = i11
            qp[b, 2, py, px] = i22
            qp[b, 3, py, px] = i01
            qp[b, 4, py, px] = i02
            qp[b, 5, py, px] = i12
            qp[b, 6, py, px] = dm0
            qp[b, 7, py, px] = dm1
            qp[b, 8, py, px] = dm2
            qp[b, 9, py, px] = m0 * dm0 + m1 * dm1 + m2 * dm2
            qp[b, 10, py, px] = 1.0
    return qp


def _bregman_update(
    zs,
    w,
    dys,
    dxs,
    lam,
    state,
    read,
    write,
    scale_in,
    inv_out,
    rhs,
    halo,
    adj,
    halo2,
    stats,
    block,
    k0,
    k1,
):  # pragma: no cover - compiled
    """A Split-Bregman update of ``StencilL1Term``: the new state and the right-hand side.

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
        _zero_rows(rhs, r0, r1)
        if measure:
            halo2[blk] = 0.0
            stats[blk] = 0.0
            _zero_rows(adj, r0, r1)
        for r in range(r0, r1):
            b = r // h
            y = r - b * h
            a1, a2, a3, a4 = acc[0], acc[1], acc[2], acc[3]
            for k in range(nk):
                dy = dys[k]
                dx = dxs[k]
                if y + dy >= h:
                    continue
                x0, n = _span(dx, wd)
                wr = w[b, k, y, x0 : x0 + n]
                rj = r + dy
                for c in range(nc):
                    oi = rhs[b, c, y, x0 : x0 + n]
                    if rj < r1:
                        oj = rhs[b, c, y + dy, x0 + dx : x0 + dx + n]
                    else:
                        oj = halo[blk, rj - r1, c, x0 + dx : x0 + dx + n]
                    bb = bbuf[:n]
                    _read_state(state, b, c, k, y, x0, bb, read, quant, scale_in)
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
                        ai = adj[b, c, y, x0 : x0 + n]
                        if rj < r1:
                            aj = adj[b, c, y + dy, x0 + dx : x0 + dx + n]
                        else:
                            aj = halo2[blk, rj - r1, c, x0 + dx : x0 + dx + n]
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
def _measured_pairs(zi, zj, wr, bb, cb, nw, a1, a2, a3, a4, lam):  # pragma: no cover
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


def _add_halos(rhs, halo, block):  # pragma: no cover - compiled
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


def _affinity_exponent(feat, mask, dys, dxs, scale, floor, out, r0, r1):  # pragma: no cover
    """``out_k(i) = scale · ‖f_i − f_j‖²``, ``j = i + o_k``: the exponent of the affinity.

    ``-inf`` (a weight of 0 once exponentiated) where the exponent is below ``floor`` (see
    ``reflectance_terms.MIN_EXPONENT``), where the pair leaves the image and, with ``mask``
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
            x0, n = _span(dx, wd)
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
                _mask_row(mask, b, y, dy, dx, x0, n, o, ninf)
    return out


def _scale_by_factor(out, sem, a_l, a_m, r0, r1):  # pragma: no cover - compiled
    """``out *= a_l + a_m · sem`` over the rows ``r0 .. r1 - 1`` of ``(B·K·H, W)`` views."""
    for r in range(r0, r1):
        o = out[r]
        s = sem[r]
        for t in range(o.shape[0]):
            o[t] *= a_l + a_m * s[t]
    return out


@njit(inline="always")
def _zero_rows(out, r0, r1):  # pragma: no cover - compiled
    """Zero rows ``r0 .. r1 − 1`` (of the batch's ``B·H``) of ``out`` ``(B, C, H, W)``."""
    h = out.shape[2]
    for r in range(r0, r1):
        b = r // h
        y = r - b * h
        for c in range(out.shape[1]):
            out[b, c, y, :] = 0.0


@njit(inline="always")
def _read_state(state, b, c, k, y, x0, bb, read, quant, scale_in):  # pragma: no cover
    """A run of ``len(bb)`` Bregman variables from ``state`` (decoded when fixed point), or 0."""
    n = bb.shape[0]
    if read and quant:
        sq = state[b, c, k, y, x0 : x0 + n]
        for t in range(n):
            bb[t] = sq[t] * scale_in
    elif read:
        bb[:] = state[b, c, k, y, x0 : x0 + n]
    else:
        bb[:] = 0.0


@njit(inline="always")
def _span(dx, wd):  # pragma: no cover - compiled
    """``(x0, n)``: the first column and the count of pixels ``i`` whose ``i + dx`` is inside."""
    x0 = max(0, -dx)
    return x0, min(wd, wd - dx) - x0


@njit(inline="always")
def _mask_row(mask, b, y, dy, dx, x0, n, o, value):  # pragma: no cover - compiled
    mi = mask[b, 0, y, x0 : x0 + n]
    mj = mask[b, 0, y + dy, x0 + dx : x0 + dx + n]
    for t in range(n):
        if not (mi[t] and mj[t]):
            o[t] = value


_jit = njit(nogil=True, cache=True, fastmath=True, boundscheck=False)
# the product keeps IEEE semantics (no reassociation of its sums)
gather = njit(nogil=True, cache=True, boundscheck=False)(_gather)
gather_parallel = njit(parallel=True, nogil=True, cache=True, boundscheck=False)(_gather_all)
matting_weights = _jit(_matting_weights)
# IEEE semantics: the replayed Bregman variable is the one the torch path would have stored
bregman_update = njit(nogil=True, cache=True, boundscheck=False)(_bregman_update)
add_halos = njit(nogil=True, cache=True, boundscheck=False)(_add_halos)
# the window statistics keep IEEE semantics, as the torch ops that they replace
matting_windows = njit(nogil=True, cache=True, boundscheck=False)(_matting_windows)
# IEEE semantics: fast-math would let LLVM assume that no value is infinite, and the exponent
# marks the pairs without weight by -inf
affinity_exponent = njit(nogil=True, cache=True, boundscheck=False)(_affinity_exponent)
scale_by_factor = njit(nogil=True, cache=True, boundscheck=False)(_scale_by_factor)
