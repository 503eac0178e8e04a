"""The numba kernels of the matting Laplacian's 5×5 stencil (``MattingQuadratic.as_stencil``).

:func:`matting_windows` computes every 3×3 window's summands once, :func:`matting_weights` sums
them into the pair weights; both over a band of rows, without the GIL.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from torchiid.priors.kernel_rows import Array, span

__all__ = ["matting_weights", "matting_windows"]


def _matting_weights(
    qp: Array, img: Array, dys: Array, dxs: Array, out: Array, r0: int, r1: int
) -> Array:  # pragma: no cover - compiled
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
            x0, n = span(dx, wd)
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


def _matting_windows(
    img: Array, mask: Array, eps: float, qp: Array, r0: int, r1: int
) -> Array:  # pragma: no cover - compiled
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


matting_weights = njit(nogil=True, cache=True, fastmath=True, boundscheck=False)(_matting_weights)
# the window statistics keep IEEE semantics, as the torch ops that they replace
matting_windows = njit(nogil=True, cache=True, boundscheck=False)(_matting_windows)
