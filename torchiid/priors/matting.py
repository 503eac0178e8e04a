"""Levin et al.'s matting Laplacian as the propagation term ``S_p`` (paper Eq. 3).

For 3x3 windows ``w_k`` fully inside the image,

``L_ij = sum_{k: i, j in w_k} ( delta_ij - (1 + (I_i - mu_k)^T (Sigma_k + eps/9 U)^{-1}
(I_j - mu_k)) / 9 )``

(Levin, Lischinski & Weiss 2008, Eq. 12), ``mu_k`` and ``Sigma_k`` the mean and covariance of the
base image's colours in ``w_k``. ``L`` is a sum of per-window PSD blocks, so it is PSD with
``L 1 = 0`` (it equals ``M^T W M`` with ``M`` the per-window centring/projection operator).

:class:`MattingQuadratic` applies ``L`` without assembling its 81 entries per window, using box
filters as He, Sun & Tang (2010, "Fast matting using large kernel matting Laplacian matrices"):
``(L p)_i = n_i p_i - I_i^T sum_{k ∋ i} a_k - sum_{k ∋ i} b_k`` with
``a_k = Delta_k^{-1} (mean_k(I p) - mu_k mean_k(p))`` and ``b_k = mean_k(p) - a_k^T mu_k``.
:meth:`MattingQuadratic.to_sparse` assembles the windows (the reference).

The window statistics are computed in float64 and stored in the working dtype. The base image is
linear RGB in ``[0, 1]`` (the scale that ``eps = 1e-5`` assumes).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from torchiid.core.check import check_image
from torchiid.core.exceptions import ImageError, ShapeError
from torchiid.priors import kernels
from torchiid.priors.quadratic import QuadraticTerm, StencilQuadratic
from torchiid.priors.stencil import Stencil, half_offsets

__all__ = ["MattingQuadratic", "matting_laplacian", "matting_stencil", "smooth_base"]


def _box_valid(x: torch.Tensor) -> torch.Tensor:
    """3x3 window sums of ``(..., H, W)`` over windows fully inside: ``(..., H-2, W-2)``."""
    x = x[..., :-2, :] + x[..., 1:-1, :] + x[..., 2:, :]
    return x[..., :-2] + x[..., 1:-1] + x[..., 2:]


def _box_adjoint(a: torch.Tensor) -> torch.Tensor:
    """Adjoint of :func:`_box_valid`: ``(..., H-2, W-2) -> (..., H, W)``."""
    return _box_valid(F.pad(a, (2, 2, 2, 2)))


def _check_base(base: torch.Tensor, mask: torch.Tensor | None) -> None:
    """The checks every construction of ``S_p`` makes on its base image and mask."""
    if base.dim() == 4 and min(base.shape[-2:]) < 3:
        raise ImageError(
            f"the matting Laplacian needs at least 3x3 pixels, got {tuple(base.shape)}"
        )
    check_image(base, "base image", channels=3, min_side=3, nonnegative=False)
    b, _, h, w = base.shape
    if mask is not None and mask.shape != (b, 1, h, w):
        raise ShapeError(f"expected mask of shape {(b, 1, h, w)}, got {tuple(mask.shape)}")


def _centred64(base: torch.Tensor) -> torch.Tensor:
    """The base image in float64 minus its per-image colour mean (L is shift-invariant)."""
    i64 = base.to(torch.float64)
    return i64 - i64.mean(dim=(2, 3), keepdim=True)


def _compiled_stencil(qp: torch.Tensor, i64: torch.Tensor, dtype: torch.dtype) -> StencilQuadratic:
    """The 5×5 stencil term from the window summands ``qp`` by the compiled weights pass."""
    _, _, h, w = i64.shape
    stencil = Stencil(h, w, half_offsets(5), device=i64.device)
    weights = kernels.matting_weights(qp, i64, stencil.offsets, dtype)
    return StencilQuadratic(stencil, weights, zero_invalid=False)  # 0 there already


def _inv_sym3(c: torch.Tensor) -> torch.Tensor:
    """Inverse of symmetric positive-definite 3x3 matrices ``(B, 3, 3, ...)`` by ``L D Lᵀ``.

    Vectorised over all windows (batched LAPACK calls cost microseconds per 3x3 matrix). The
    closed-form ``L D Lᵀ`` factorisation is backward stable for SPD matrices, so the inverse is
    accurate to about ``κ · ε``. The adjugate over the cofactor-expansion determinant is not: on
    a window with one outlier pixel (a base value of 220 among values near 2, condition number
    7.5e7) it loses enough of the determinant to give the window's block of the Laplacian a
    negative eigenvalue, and the shading system is then not positive definite.
    """
    a, b, cc, d, e, f = c[:, 0, 0], c[:, 0, 1], c[:, 0, 2], c[:, 1, 1], c[:, 1, 2], c[:, 2, 2]
    l21, l31 = b / a, cc / a
    d2 = d - l21 * b
    l32 = (e - l31 * b) / d2
    d3 = f - l31 * cc - l32 * l32 * d2
    # rows of L⁻¹: (1, 0, 0), (−l21, 1, 0), (m, −l32, 1); A⁻¹ = Σ_k row_kᵀ row_k / d_k
    m = l21 * l32 - l31
    r1, r2, r3 = 1 / a, 1 / d2, 1 / d3
    i00 = r1 + l21 * l21 * r2 + m * m * r3
    i01 = -l21 * r2 - m * l32 * r3
    i02 = m * r3
    i11 = r2 + l32 * l32 * r3
    i12 = -l32 * r3
    rows = [[i00, i01, i02], [i01, i11, i12], [i02, i12, r3]]
    return torch.stack([torch.stack(r, 1) for r in rows], 1)


def smooth_base(image: torch.Tensor, sigma: float = 1.0) -> torch.Tensor:
    """Gaussian-smoothed image, the first iteration's base image of ``S_p`` (paper §3.2).

    The paper smooths with a Gaussian; the authors' earlier code used a rolling-guidance filter
    (sigma_s = 3, sigma_r = 0.1). A Gaussian with ``sigma`` pixels (reflect padding) is used here.

    Shape:
        ``(B, C, H, W) -> (B, C, H, W)``.
    """
    if sigma <= 0:
        return image
    r = max(1, math.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, device=image.device, dtype=image.dtype)
    g = torch.exp(-(t**2) / (2 * sigma**2))
    taps = (g / g.sum()).tolist()
    h, w = image.shape[-2:]
    mode = "reflect" if r < min(h, w) else "replicate"  # tiny images: replicate padding
    x = F.pad(image, (r, r, r, r), mode=mode)
    # separable, as shifted sums of the padded image: a depthwise conv2d on the CPU is about
    # ten times slower and, on a batch, builds large temporary buffers
    return _taps(_taps(x, taps, -2, h), taps, -1, w)


def _taps(x: torch.Tensor, taps: list[float], dim: int, size: int) -> torch.Tensor:
    """``Σ_k taps[k] · x[k : k + size]`` along ``dim``."""
    out = x.narrow(dim, 0, size) * taps[0]
    for k in range(1, len(taps)):
        out.add_(x.narrow(dim, k, size), alpha=taps[k])
    return out


class MattingQuadratic(QuadraticTerm):
    """The matting Laplacian of a base image as a quadratic term ``s^T L s`` (Eq. 3).

    Args:
        base: ``(B, 3, H, W)`` linear RGB base image, ``H, W >= 3``.
        eps: Levin's regulariser ``epsilon`` (paper: 1e-5).
        mask: optional ``(B, 1, H, W)`` bool; windows with a pixel outside it are dropped.

    Raises:
        ShapeError / ImageError: bad base image or mask.

    Shape:
        unknowns ``(B, 1, H, W)``.
    """

    def __init__(
        self, base: torch.Tensor, eps: float = 1e-5, mask: torch.Tensor | None = None
    ) -> None:
        _check_base(base, mask)
        b, _, h, w = base.shape
        dtype = base.dtype
        i64 = _centred64(base)
        mu = _box_valid(i64) / 9  # (B, 3, h, w)
        outer = i64.unsqueeze(1) * i64.unsqueeze(2)  # (B, 3, 3, H, W)
        cov = _box_valid(outer) / 9 - mu.unsqueeze(1) * mu.unsqueeze(2)
        cov = cov + (eps / 9) * torch.eye(3, dtype=torch.float64, device=base.device).view(
            1, 3, 3, 1, 1
        )
        inv = _inv_sym3(cov)
        valid = torch.ones(b, 1, h - 2, w - 2, dtype=torch.float64, device=base.device)
        if mask is not None:
            valid = (_box_valid(mask.to(torch.float64)) > 8.5).to(torch.float64)
        # float64 statistics kept for the one-time diagonal / stencil conversion
        self._stats64 = (i64, mu, inv, valid)
        self.base = i64.to(dtype)
        self.mu = mu.to(dtype)
        self.inv = inv.to(dtype)
        self.valid = valid.to(dtype)
        self.eps = float(eps)
        self.count = _box_adjoint(valid).to(dtype)  # windows containing each pixel
        self._diag: torch.Tensor | None = None
        self.shape = (b, 1, h, w)
        self.dtype = dtype
        self.device = base.device

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``L x`` by box filters (He et al. 2010), no assembled matrix."""
        self._check(x)
        p = x - x.mean(dim=(2, 3), keepdim=True)  # L 1 = 0; centring limits cancellation
        pm = _box_valid(p) / 9
        ipm = _box_valid(self.base * p) / 9
        c = ipm - self.mu * pm  # (B, 3, h, w) window covariance of I and p
        a = torch.einsum("bijyx,bjyx->biyx", self.inv, c)
        bb = pm - (a * self.mu).sum(1, keepdim=True)
        sa = _box_adjoint(self.valid * a)
        sb = _box_adjoint(self.valid * bb)
        return self.count * p - (self.base * sa).sum(1, keepdim=True) - sb

    def diagonal(self) -> torch.Tensor:
        """``diag(L)`` (computed on first use, in float64)."""
        if self._diag is None:
            i64, mu, inv, valid = self._stats64
            # sum_k v_k [8/9 - (I_i - mu_k)^T D_k (I_i - mu_k) / 9]
            s_d = _box_adjoint(valid.unsqueeze(1) * inv)  # (B, 3, 3, H, W)
            dmu = (inv * mu.unsqueeze(1)).sum(2)
            s_dmu = _box_adjoint(valid * dmu)
            s_mdm = _box_adjoint(valid * (mu * dmu).sum(1, keepdim=True))
            quad = (i64.unsqueeze(1) * s_d * i64.unsqueeze(2)).sum((1, 2)).unsqueeze(1)
            quad = quad - 2 * (i64 * s_dmu).sum(1, keepdim=True) + s_mdm
            diag = _box_adjoint(valid) * 8 / 9 - quad / 9
            self._diag = diag.clamp_min(0).to(self.dtype)
        return self._diag

    def as_stencil(self, band_rows: int | None = None) -> StencilQuadratic:
        """The same Laplacian as a signed 5x5 pair stencil (12 offsets), for fast products.

        Since ``L 1 = 0``, ``L = sum_{i<j} (-L_ij) (e_i - e_j)(e_i - e_j)^T`` and ``L_ij`` is
        non-zero only for ``|i - j|_inf <= 2``. The pair weights
        ``-L_ij = (n + I_i^T S I_j - (I_i + I_j)^T T + U) / 9`` use the sums ``n, S, T, U`` of
        ``v_k, v_k D_k, v_k D_k mu_k, v_k mu_k^T D_k mu_k`` over the windows containing both
        pixels (rectangle sums, float64). Some weights are negative; the sum stays PSD.
        One 5x5 stencil product costs a fraction of the box-filter product and merges with
        the 3x3 terms (:class:`~torchiid.priors.quadratic.SumQuadratic`).

        Args:
            band_rows: rows per band of the float64 computation (default: about 49k pixels a
                band, 96 rows at 512 px width). The result does not depend on it.
        """
        b, _, h, w = self.shape
        if band_rows is None:
            band_rows = max(8, -(-49152 // w))
        img, mu, inv, v = self._stats64
        sym = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
        dmu = (inv * mu.unsqueeze(1)).sum(2)  # (B, 3, h-2, w-2)
        q = torch.cat(
            [inv[:, a, c].unsqueeze(1) for a, c in sym]
            + [dmu, (mu * dmu).sum(1, keepdim=True), torch.ones_like(v)],
            dim=1,
        )
        qp = F.pad(q * v, (2, 2, 2, 2))  # window (wy, wx) at padded (wy + 2, wx + 2)
        if kernels.usable(qp, img):
            return _compiled_stencil(qp, img, self.dtype)
        stencil = Stencil(h, w, half_offsets(5), device=self.device)
        ip = F.pad(img, (2, 2, 0, 2))
        weights = torch.zeros(b, stencil.num_offsets, h, w, dtype=self.dtype, device=self.device)
        for y0 in range(0, h, band_rows):  # row bands keep the float64 temporaries in cache
            y1 = min(h, y0 + band_rows)
            rows = [qp[:, :, 2 + y0 : 2 + y1]]  # rows[t]: sum over wy in [y - t, y]
            for t in (1, 2):
                rows.append(rows[-1] + qp[:, :, 2 - t + y0 : 2 - t + y1])
            ii = img[:, :, y0:y1]
            for k, (dy, dx) in enumerate(stencil.offsets):
                # windows containing i and j = i + (dy, dx): wy in [y + dy - 2, y],
                # wx in [max(x, x + dx) - 2, min(x, x + dx)]
                r = rows[2 - dy]
                lo, hi = max(0, dx), min(0, dx)  # wx + 2 - x in [lo, hi + 2]
                s = r[..., lo : lo + w]
                for t in range(lo + 1, hi + 3):
                    s = s + r[..., t : t + w]
                ij = ip[:, :, y0 + dy : y1 + dy, 2 + dx : 2 + dx + w]  # I_j (0 outside)
                quad = s[:, 0] * ii[:, 0] * ij[:, 0] + s[:, 1] * ii[:, 1] * ij[:, 1]
                quad = quad + s[:, 2] * ii[:, 2] * ij[:, 2]
                for n, (a, c) in enumerate(sym[3:], start=3):
                    quad = quad + s[:, n] * (ii[:, a] * ij[:, c] + ii[:, c] * ij[:, a])
                lin = (s[:, 6:9] * (ii + ij)).sum(1)
                weights[:, k, y0:y1] = (s[:, 10] + quad - lin + s[:, 9]) / 9
        return StencilQuadratic(stencil, weights)

    def window_blocks(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-window 9x9 blocks and their pixel indices (dropped windows are zero).

        Returns:
            ``(blocks (B, nw, 9, 9), index (nw, 9))`` with flat pixel indices per image.
        """
        b, _, h, w = self.shape
        pix = torch.arange(h * w, device=self.device).view(1, 1, h, w).to(torch.float64)
        idx = F.unfold(pix, 3).round().long()[0].t()  # (nw, 9)
        cols = F.unfold(self.base.to(torch.float64), 3).view(b, 3, 9, -1)  # (B, 3, 9, nw)
        x = (
            cols.permute(0, 3, 2, 1)
            - self.mu.to(torch.float64).flatten(2).transpose(1, 2)[:, :, None, :]
        )  # (B, nw, 9, 3)
        inv = self.inv.to(torch.float64).flatten(3).permute(0, 3, 1, 2)  # (B, nw, 3, 3)
        g = (
            torch.eye(9, dtype=torch.float64, device=self.device)
            - (1 + x @ inv @ x.transpose(2, 3)) / 9
        )
        g = g * self.valid.to(torch.float64).flatten(1)[:, :, None, None]
        return g, idx

    def to_sparse(self) -> torch.Tensor:
        """The assembled Laplacian, sparse COO ``(B H W, B H W)`` in the working dtype."""
        b, _, h, w = self.shape
        g, idx = self.window_blocks()
        n = h * w
        off = (torch.arange(b, device=self.device) * n).view(b, 1, 1, 1)
        rows = (idx[None, :, :, None] + off).expand(b, -1, 9, 9)
        cols = (idx[None, :, None, :] + off).expand(b, -1, 9, 9)
        ind = torch.stack([rows.reshape(-1), cols.reshape(-1)])
        return torch.sparse_coo_tensor(
            ind, g.reshape(-1).to(self.dtype), (b * n, b * n), check_invariants=False
        ).coalesce()


def matting_laplacian(
    base: torch.Tensor, eps: float = 1e-5, mask: torch.Tensor | None = None
) -> MattingQuadratic:
    """The propagation term ``S_p`` of Eq. 3 on ``base`` (see :class:`MattingQuadratic`).

    Args:
        base: ``(B, 3, H, W)`` linear RGB base image: the smoothed input on the first iteration
            (:func:`smooth_base`), the previous reflectance afterwards.
        eps: regulariser, paper value 1e-5.
        mask: optional ``(B, 1, H, W)`` bool region; windows leaving it are dropped.

    Returns:
        :class:`MattingQuadratic`.
    """
    return MattingQuadratic(base, eps=eps, mask=mask)


def matting_stencil(
    base: torch.Tensor, eps: float = 1e-5, mask: torch.Tensor | None = None
) -> StencilQuadratic:
    """``S_p`` of Eq. 3 as its signed 5×5 pair stencil: ``matting_laplacian(...).as_stencil()``.

    What the shading stage uses. Where the compiled kernels apply
    (:func:`~torchiid.priors.kernels.usable`) the window statistics and the pair weights are
    computed in two passes over the image, without the float64 torch temporaries of
    :class:`MattingQuadratic` (``python tools/bench_kernels.py`` compares the two); otherwise it
    is exactly ``matting_laplacian(base, eps, mask).as_stencil()``.

    Args:
        base: ``(B, 3, H, W)`` linear RGB base image (see :func:`matting_laplacian`).
        eps: regulariser, paper value 1e-5.
        mask: optional ``(B, 1, H, W)`` bool region; windows leaving it are dropped.

    Returns:
        :class:`~torchiid.priors.quadratic.StencilQuadratic` in ``base``'s dtype.
    """
    if not kernels.usable(base):
        return matting_laplacian(base, eps=eps, mask=mask).as_stencil()
    _check_base(base, mask)
    i64 = _centred64(base)
    return _compiled_stencil(kernels.matting_window_terms(i64, eps, mask), i64, base.dtype)
