"""Colour Retinex baseline of Grosse et al. 2009 (MIT intrinsic images, ``color_retinex``).

Grosse, Johnson, Adelson & Freeman, "Ground truth dataset and baseline evaluations for
intrinsic image algorithms", ICCV 2009, Section 5.2. The log image's finite differences
between 4-neighbours are classified as reflectance changes when their chromaticity part is
large or their gray part is large; the gray log-reflectance is the least-squares
reintegration of the kept differences (a masked Poisson equation), and the gray shading is
the gray image divided by it.

Details that follow the reference ``color_retinex`` (learned from it, not copied):

- The image is clamped from below at ``eps = 3/257 ≈ 0.0117``: the reference reads 16-bit
  PNGs divided by 255 (a 0–257 scale) and clips at 3.
- Differences ``d_c`` of ``log I_c`` per channel; gray part ``ḡ = mean_c d_c``, chromaticity
  part ``d_c − ḡ``. A difference is kept when ``‖d − ḡ‖₂ > threshold_color`` or
  ``|ḡ| > threshold_gray``. The value kept is the difference of ``log mean_c(I)`` (the log of
  the gray image, not the mean of the logs), as in the reference.
- Only differences with both pixels inside the mask enter the Poisson equation. It is
  solved in float64 by CG (:func:`torchiid.solvers.pcg.pcg`) preconditioned with the
  pseudo-inverse of the *full-grid* Neumann Laplacian (FFT/DCT Poisson solver) restricted
  to the masked pixels, which takes tens of iterations where Jacobi takes thousands.
  The solution is defined up to a constant per connected mask component; the gray
  reflectance is scaled so its maximum inside the mask is 1.
- Defaults ``threshold_gray = 0.075``, ``threshold_color = 1.0`` are points of the
  reference's parameter grid (``logspace(-1.5, 0, 5)``).

Outputs satisfy ``image == reflectance · shading`` (linear); outside the mask the shading
is 1 and the reflectance is the image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch

from torchiid.baselines.result import BaselineResult
from torchiid.core.check import as_mask, check_image
from torchiid.core.exceptions import ParameterError
from torchiid.model import Decomposition, full_resolution_layers
from torchiid.params import Parameters
from torchiid.solvers.pcg import pcg

__all__ = ["color_retinex", "ColorRetinex", "RetinexResult", "retinex_decomposition"]

logger = logging.getLogger(__name__)

GROSSE_EPS = 3.0 / 257.0


@dataclass(frozen=True, eq=False)
class RetinexResult(BaselineResult):
    """Result of :func:`color_retinex`, **linear**; ``reflectance * shading == image``.

    Attributes:
        reflectance: ``(B, 3, H, W)`` reflectance; the image itself outside the mask.
        shading: ``(B, 1, H, W)`` gray shading; 1 outside the mask.
    """


def _grad_y(x: torch.Tensor) -> torch.Tensor:
    return x[..., 1:, :] - x[..., :-1, :]


def _grad_x(x: torch.Tensor) -> torch.Tensor:
    return x[..., :, 1:] - x[..., :, :-1]


def _grad_y_t(v: torch.Tensor) -> torch.Tensor:
    """Adjoint of :func:`_grad_y` (``(.., H-1, W) -> (.., H, W)``)."""
    out = v.new_zeros(*v.shape[:-2], v.shape[-2] + 1, v.shape[-1])
    out[..., 1:, :] += v
    out[..., :-1, :] -= v
    return out


def _grad_x_t(v: torch.Tensor) -> torch.Tensor:
    out = v.new_zeros(*v.shape[:-1], v.shape[-1] + 1)
    out[..., :, 1:] += v
    out[..., :, :-1] -= v
    return out


def _neumann_pinv(f: torch.Tensor) -> torch.Tensor:
    """Apply the pseudo-inverse of the full-grid 5-point Neumann Laplacian to ``f``.

    The half-sample symmetric extension of ``f`` to ``2H × 2W`` turns the Neumann problem
    into a periodic one, diagonalised by the FFT (the DCT-II in disguise); the constant
    mode is dropped. Shape: ``(B, 1, H, W) -> (B, 1, H, W)``.
    """
    h, w = f.shape[-2:]
    ext = torch.cat([f, f.flip(-2)], dim=-2)
    ext = torch.cat([ext, ext.flip(-1)], dim=-1)
    spec = torch.fft.rfft2(ext)
    ky = torch.arange(2 * h, dtype=f.dtype, device=f.device)
    kx = torch.arange(w + 1, dtype=f.dtype, device=f.device)
    lam = (2 - 2 * torch.cos(torch.pi * ky / h))[:, None] + (2 - 2 * torch.cos(torch.pi * kx / w))
    inv = torch.where(lam > 1e-12, 1.0 / torch.where(lam > 1e-12, lam, 1.0), 0.0)
    return torch.fft.irfft2(spec * inv, s=(2 * h, 2 * w))[..., :h, :w]


def _classify(log_image: torch.Tensor, grad, tg: float, tc: float) -> torch.Tensor:
    """Reflectance-change mask of the differences of ``log_image`` (B, 3, H, W)."""
    d = grad(log_image)
    gray = d.mean(dim=1, keepdim=True)
    chroma = torch.linalg.vector_norm(d - gray, dim=1, keepdim=True)
    return (chroma > tc) | (gray.abs() > tg)


def color_retinex(
    image: torch.Tensor,
    mask: torch.Tensor | None = None,
    threshold_gray: float = 0.075,
    threshold_color: float = 1.0,
    eps: float = GROSSE_EPS,
    tol: float = 1e-8,
    max_iter: int = 10000,
) -> RetinexResult:
    """Colour Retinex decomposition (Grosse et al. 2009).

    Args:
        image: linear RGB ``(B, 3, H, W)``, values ~[0, 1].
        mask: pixels to decompose, ``(B, 1, H, W)``, ``(B, H, W)`` or ``(H, W)``, bool or
            {0, 1}; ``None`` for all.
        threshold_gray: threshold on ``|mean_c ∂ log I_c|``.
        threshold_color: threshold on the chromaticity-difference norm.
        eps: lower clamp of the image before the log (Grosse's 3 on a 0–257 scale).
        tol: relative residual of the CG Poisson solve.
        max_iter: CG iteration cap (a :class:`ConvergenceWarning` is emitted if reached).

    Returns:
        :class:`RetinexResult` with ``reflectance`` ``(B, 3, H, W)`` and ``shading``
        ``(B, 1, H, W)``, linear, dtype of ``image``, with ``reflectance * shading == image``.

    Shape:
        - image: ``(B, 3, H, W)``; mask: ``(B, 1, H, W)``.

    Example:
        >>> img = torch.rand(1, 3, 16, 16) + 0.1
        >>> out = color_retinex(img)
        >>> out.reflectance.shape, out.shading.shape
        (torch.Size([1, 3, 16, 16]), torch.Size([1, 1, 16, 16]))
    """
    check_image(image, "image", channels=3, min_side=2)
    if threshold_gray < 0 or threshold_color < 0 or not eps > 0:
        raise ParameterError(
            "expected threshold_gray >= 0, threshold_color >= 0 and eps > 0, got "
            f"{threshold_gray}, {threshold_color}, {eps}"
        )
    m = as_mask(mask, image)
    x = image.double()
    log_i = torch.log(x.clamp_min(eps))
    gray_i = x.mean(dim=1, keepdim=True).clamp_min(eps)
    log_g = torch.log(gray_i)

    mf = m.double()
    wy = mf[..., 1:, :] * mf[..., :-1, :]
    wx = mf[..., :, 1:] * mf[..., :, :-1]
    ty = torch.where(_classify(log_i, _grad_y, threshold_gray, threshold_color), _grad_y(log_g), 0)
    tx = torch.where(_classify(log_i, _grad_x, threshold_gray, threshold_color), _grad_x(log_g), 0)

    deg = torch.zeros_like(mf)  # node degree = diagonal of the masked graph Laplacian
    deg[..., 1:, :] += wy
    deg[..., :-1, :] += wy
    deg[..., :, 1:] += wx
    deg[..., :, :-1] += wx
    isolated = (deg == 0).double()  # no edge: identity row, solution 0

    def matvec(v: torch.Tensor) -> torch.Tensor:
        return _grad_y_t(wy * _grad_y(v)) + _grad_x_t(wx * _grad_x(v)) + isolated * v

    def precond(r: torch.Tensor) -> torch.Tensor:
        # SPD block preconditioner: the full-grid Neumann Laplacian's pseudo-inverse,
        # restricted to the pixels with edges; identity on isolated pixels
        inside = 1.0 - isolated
        return inside * _neumann_pinv(inside * r) + isolated * r

    rhs = _grad_y_t(wy * ty) + _grad_x_t(wx * tx)
    result = pcg(matvec, rhs, precond=precond, tol=tol, max_iter=max_iter)
    logger.debug("color_retinex: CG %d iterations, residual %s", result.iterations, result.residual)
    log_r = result.x
    # normalisation: gray reflectance max inside the mask is 1 (0 shift for an empty mask)
    top = torch.where(m, log_r, -torch.inf).amax(dim=(1, 2, 3), keepdim=True)
    log_r = log_r - torch.where(torch.isfinite(top), top, 0.0)
    shading = torch.where(m, gray_i / torch.exp(log_r), 1.0)
    reflectance = x / shading
    return RetinexResult(reflectance.to(image.dtype), shading.to(image.dtype))


class ColorRetinex(torch.nn.Module):
    """Module twin of :func:`color_retinex` (thresholds fixed at construction)."""

    def __init__(self, threshold_gray: float = 0.075, threshold_color: float = 1.0) -> None:
        super().__init__()
        self.threshold_gray = threshold_gray
        self.threshold_color = threshold_color

    def forward(self, image: torch.Tensor, mask: torch.Tensor | None = None) -> RetinexResult:
        """See :func:`color_retinex`."""
        return color_retinex(image, mask, self.threshold_gray, self.threshold_color)


def retinex_decomposition(
    image: torch.Tensor,
    params: Parameters | None = None,
    *,
    mask: torch.Tensor | None = None,
    threshold_gray: float = 0.075,
    threshold_color: float = 1.0,
) -> Decomposition:
    """Colour Retinex in the output convention of :func:`torchiid.decompose`.

    The shading of :func:`color_retinex` goes through
    :func:`~torchiid.model.full_resolution_layers`, so the reflectance is an albedo in
    ``[0, 1]`` and ``shading_white`` is set, like the method's result (what
    ``torchiid decompose --method retinex`` writes).

    Args:
        image: ``(B, 3, H, W)`` linear RGB.
        params: supplies the output convention (``albedo_quantile``, ``view_quantile``,
            ``shading_floor``); default ``Parameters()``.
        mask: optional mask, nonzero inside.
        threshold_gray: see :func:`color_retinex`.
        threshold_color: see :func:`color_retinex`.

    Returns:
        :class:`~torchiid.model.Decomposition` without Stage 1 layers or iterations.
    """
    params = params if params is not None else Parameters()
    if mask is not None:
        mask = as_mask(mask, image, "mask")
    shading = color_retinex(
        image, mask, threshold_gray=threshold_gray, threshold_color=threshold_color
    ).shading
    layers = full_resolution_layers(
        image, shading.clamp_min(params.reflectance.shading_floor), None, mask, params
    )
    return Decomposition(
        reflectance=layers.reflectance,
        shading=layers.shading,
        sigma=None,
        rho=None,
        iterations=(),
        params=params,
        mask=mask,
        shading_white=layers.shading_white,
        albedo_excess=layers.albedo_excess,
        working_size=tuple(image.shape[-2:]),
    )
