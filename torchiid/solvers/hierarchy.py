"""The multigrid hierarchy: geometric aggregation, smoothed prolongation, Galerkin by probing.

Pixels are aggregated in ``block x block`` squares (the coarse grid is again an image). The
tentative prolongation ``P_t`` is piecewise constant and is smoothed once, ``P = (I - omega
D_l^{-1} A_l) P_t``, with the *local* (stencil) part ``A_l`` of the level's operator only, so
``P`` stays local (:class:`Transfer`). The coarse operator is the exact Galerkin product ``A_c =
P^T A P`` (:func:`galerkin`): its stencil part is read off probe vectors, one per colour of a
colouring of the coarse grid, and the non-local rows ``M^T W M`` become ``(M P)^T W (M P)``,
kept factored so the few LLE rows never fill the coarse matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchiid.priors.stencil import half_offsets, shift_slices
from torchiid.solvers.smoothers import lanczos_lmax
from torchiid.solvers.stencil_operator import Factor, StencilOperator

__all__ = ["Level", "Transfer", "aggregation", "galerkin"]


@dataclass(frozen=True)
class Transfer:
    """Prolongation ``P = (I - omega D_l^{-1} A_l) P_t`` and restriction ``P^T`` of one level.

    Attributes:
        block: aggregate side.
        shape: ``(H, W)`` of the fine grid.
        coarse_shape: ``(Hc, Wc)``, ``ceil(H / block)`` by ``ceil(W / block)``.
        local: ``A_l``, the level's stencil and diagonal.
        dloc_inv: ``1 / diag(A_l)`` ``(B, 1, H, W)``.
        omega: ``(B, 1, 1, 1)`` damping of the smoothing step.
    """

    block: int
    shape: tuple[int, int]
    coarse_shape: tuple[int, int]
    local: StencilOperator
    dloc_inv: torch.Tensor
    omega: torch.Tensor

    def to(self, dtype: torch.dtype) -> Transfer:
        """The same transfer with its coefficients in ``dtype``."""
        return Transfer(
            self.block,
            self.shape,
            self.coarse_shape,
            self.local.to(dtype=dtype),
            self.dloc_inv.to(dtype),
            self.omega.to(dtype),
        )

    def up(self, xc: torch.Tensor) -> torch.Tensor:
        """``P_t xc``: every coarse value copied to its aggregate."""
        s = self.block
        u = xc.repeat_interleave(s, dim=2).repeat_interleave(s, dim=3)
        return u[:, :, : self.shape[0], : self.shape[1]]

    def sum_down(self, r: torch.Tensor) -> torch.Tensor:
        """``P_t^T r``: every aggregate's sum."""
        s = self.block
        b, c, h, w = r.shape
        hc, wc = self.coarse_shape
        if (h, w) != (hc * s, wc * s):
            r = torch.nn.functional.pad(r, (0, wc * s - w, 0, hc * s - h))
        return r.reshape(b, c, hc, s, wc, s).sum(dim=(3, 5))

    def prolong(self, xc: torch.Tensor) -> torch.Tensor:
        """``P xc``: coarse ``(B, C, Hc, Wc)`` to the fine grid."""
        u = self.up(xc)
        return u - (self.omega * self.dloc_inv) * self.local.stencil_matvec(u)

    def restrict(self, r: torch.Tensor) -> torch.Tensor:
        """``P^T r``: fine ``(B, C, H, W)`` to the coarse grid."""
        return self.sum_down(r - self.omega * self.local.stencil_matvec(self.dloc_inv * r))


@dataclass
class Level:
    """One level of the hierarchy (in the cycle's dtype).

    Attributes:
        op: the level's full operator.
        dinv: ``1 / diag(op)``.
        lmax: ``(B, 1, 1, 1)`` estimate of ``lambda_max(D^{-1} A)``, with margin.
        transfer: to the next coarser level (``None`` on the coarsest).
    """

    op: StencilOperator
    dinv: torch.Tensor
    lmax: torch.Tensor
    transfer: Transfer | None = None


def aggregation(op: StencilOperator, block: int, lanczos_steps: int, omega: float) -> Transfer:
    """The smoothed aggregation of ``op``'s grid (``omega / lambda_max(D_l^{-1} A_l)`` damping)."""
    loc = op.local()
    dl_inv = 1 / loc.d
    rho = lanczos_lmax(loc.stencil_matvec, dl_inv, lanczos_steps)
    coarse = (-(-op.height // block), -(-op.width // block))
    return Transfer(block, (op.height, op.width), coarse, loc, dl_inv, omega / rho)


def galerkin(op: StencilOperator, tr: Transfer) -> StencilOperator:
    """The coarse operator ``P^T A P`` (exact): stencil by probing, factored rows by ``M P``.

    The coarse stencil's radius is ``floor((3 r + block - 1) / block)`` (5x5 stays 5x5 for
    ``block = 3``); it is read off ``(2 r_c + 1)^2`` probe vectors, each the indicator of one
    colour of a colouring in which no two coarse pixels within the radius share a colour.
    """
    h, w = tr.shape
    hc, wc = tr.coarse_shape
    b = op.batch
    dev, dt = op.device, op.dtype
    r = op.radius
    rc = max(1, (3 * r + tr.block - 1) // tr.block) if r > 0 else 1
    q = 2 * rc + 1
    yy = torch.arange(hc, device=dev).view(-1, 1)
    xx = torch.arange(wc, device=dev).view(1, -1)
    color = (yy % q) * q + (xx % q)  # (hc, wc)
    # probes in chunks of channels (memory: chunk * H * W per array)
    chunk = max(1, min(q * q, int(4e7 // max(1, b * h * w))))
    vals = torch.empty(b, q * q, hc, wc, dtype=dt, device=dev)
    for c0 in range(0, q * q, chunk):
        cs = torch.arange(c0, min(q * q, c0 + chunk), device=dev)
        e = (color.view(1, 1, hc, wc) == cs.view(1, -1, 1, 1)).to(dt).expand(b, -1, -1, -1)
        pe = tr.prolong(e.contiguous())
        vals[:, c0 : c0 + cs.numel()] = tr.restrict(tr.local.stencil_matvec(pe))
    # read the stencil: A_c[I, I + o] = vals[color(I + o)][I]
    offsets = half_offsets(q)
    a = torch.zeros(b, len(offsets), hc, wc, dtype=dt, device=dev)
    for k, (dy, dx) in enumerate(offsets):
        yi, xi, yj, xj = shift_slices(dy, dx, hc, wc)
        if yi.stop <= yi.start or xi.stop <= xi.start:
            continue
        cj = color[yj, xj]  # colour of the partner I + o
        ci = color[yi, xi]  # colour of I
        fwd = vals[:, :, yi, xi].gather(1, cj.expand(b, 1, *cj.shape))
        bwd = vals[:, :, yj, xj].gather(1, ci.expand(b, 1, *ci.shape))
        a[:, k, yi, xi] = 0.5 * (fwd + bwd)[:, 0]
    d = vals.gather(1, color.expand(b, 1, hc, wc))
    factors = [_factor_galerkin(m, wr, tr) for m, wr in op.factors]
    return StencilOperator(offsets, a, d, factors)


def _factor_galerkin(m: torch.Tensor, wr: torch.Tensor, tr: Transfer) -> Factor:
    """``M P`` for sparse rows ``M`` (exact, structured: no matrix of ``P`` is formed)."""
    s = tr.block
    h, w = tr.shape
    hc, wc = tr.coarse_shape
    loc = tr.local
    n, nc = h * w, hc * wc
    m = m.coalesce()
    (rows, cols), v = m.indices(), m.values()
    bi = cols // n
    y, x = (cols % n) // w, cols % w

    def coarse_index(bb: torch.Tensor, yy: torch.Tensor, xx: torch.Tensor) -> torch.Tensor:
        return bb * nc + (yy // s) * wc + (xx // s)

    out_r = [rows]
    out_c = [coarse_index(bi, y, x)]
    out_v = [v]
    # - omega M D^-1 A_l P_t: entry (r, J(i + o)) += -omega v / d_i * A_l[i, i + o]
    coef = -tr.omega.reshape(-1)[bi] * v * tr.dloc_inv.reshape(-1)[cols]
    full: list[tuple[tuple[int, int], tuple[int, int] | None]] = [((0, 0), None)]
    full += [(o, (k, 1)) for k, o in enumerate(loc.offsets)]
    full += [((-o[0], -o[1]), (k, -1)) for k, o in enumerate(loc.offsets)]
    af = loc.a.reshape(loc.batch, len(loc.offsets), n)
    for (dy, dx), which in full:
        yj, xj = y + dy, x + dx
        inside = (yj >= 0) & (yj < h) & (xj >= 0) & (xj < w)
        if which is None:
            aij = loc.d.reshape(-1)[cols]
        else:
            k, sign = which
            src = cols % n if sign > 0 else ((yj.clamp(0, h - 1)) * w + xj.clamp(0, w - 1))
            aij = af[bi, k, src]
        keep = inside & (aij != 0)
        out_r.append(rows[keep])
        out_c.append(coarse_index(bi[keep], yj[keep], xj[keep]))
        out_v.append((coef * aij)[keep])
    mc = torch.sparse_coo_tensor(
        torch.stack([torch.cat(out_r), torch.cat(out_c)]),
        torch.cat(out_v),
        (m.shape[0], m.shape[1] // n * nc),
        check_invariants=False,
    ).coalesce()
    return mc, wr
