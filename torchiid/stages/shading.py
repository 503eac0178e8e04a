"""Stage 1: the L2 shading solve (paper §3.2, Eqs. 1-5).

Minimises ``Psi(s) = lambda_g (S_c + S_p) + lambda_m S_m + lambda_l S_l`` over the log-shading
``s = log sigma`` of a batch of **linear RGB** images, as one block-diagonal sparse SPD system
solved by batched Jacobi-preconditioned CG (:func:`torchiid.solvers.pcg.pcg`).

Normalisation. Every term annihilates constants (``S_l`` fixes ``s`` only up to a shift of
each connected group of pixels), so a tiny anchor ``alpha * sum_i (s_i - t)^2`` over the region
makes the system positive definite, with ``alpha = anchor * mean(diag(Psi))`` and ``t`` the
mean of ``log p`` over the region (``p`` = channel-mean intensity, clamped to ``dark_eps``).
Because ``Psi 1 = 0``, the exact minimiser then has mean ``s`` equal to ``t``: the geometric
mean of the shading equals that of the intensity (reflectance's geometric mean is about 1).
After the solve ``s`` is shifted to satisfy this exactly (removing float round-off drift).

Masks. With ``mask`` every term drops the pairs, windows and rows that touch a pixel outside;
outside pixels are pinned to ``s = 0`` (``sigma = 1``, ``rho = I``) and do not enter the solve,
so the masked object is decomposed by itself.

Speed. The products never touch a sparse matrix: ``S_l`` and ``S_m`` are 3x3 stencils, ``S_p``
is converted once to an equivalent signed 5x5 stencil (:meth:`MattingQuadratic.as_stencil`),
and all three merge into one 12-offset shifted product; ``S_c`` is a small sparse product.
Without a warm start, ``levels > 1`` first solves 2x-downsampled copies of the problem and
upsamples their solution as the initial guess (cascadic CG): the Jacobi-PCG iteration count on
these near-binary, strongly varying weights is dominated by smooth, low-frequency error that the
coarse levels remove cheaply. The assembled torch sparse matrices (``to_sparse()`` of every
term) are the tested reference.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from torchiid.core.cache import InputKey, input_key
from torchiid.core.check import check_finite, check_image, check_shape
from torchiid.core.exceptions import ConvergenceWarning, ParameterError, ShapeError
from torchiid.priors.lle import lle_term
from torchiid.priors.matting import matting_laplacian, smooth_base
from torchiid.priors.quadratic import QuadraticTerm, SumQuadratic
from torchiid.priors.shading_terms import (
    intensity,
    midlevel_term,
    pixel_confidence,
    retinex_term,
    shading_stencil,
)
from torchiid.solvers.pcg import pcg

__all__ = [
    "ShadingDiagnostics",
    "ShadingResult",
    "ShadingSystemCache",
    "build_shading_system",
    "solve_shading",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ShadingDiagnostics:
    """What the shading solve did.

    Attributes:
        iterations: PCG iterations (the batch's maximum).
        residual: ``(B,)`` final relative residual ``||b - A s|| / ||b||`` per image.
        converged: whether every image reached ``tol``.
        times: seconds spent building each term (``"S_c"``, ``"S_p"``, ``"S_m"``, ``"S_l"``),
            in the coarse-to-fine warm start (``"coarse"``, all coarser levels) and in the
            full-resolution PCG (``"solve"``).
        terms: names of the active terms.
    """

    iterations: int
    residual: torch.Tensor
    converged: bool
    times: dict[str, float] = field(default_factory=dict)
    terms: tuple[str, ...] = ()


@dataclass(frozen=True)
class ShadingResult:
    """Output of :func:`solve_shading` (linear RGB, ``image == reflectance * shading``).

    Attributes:
        log_shading: ``(B, 1, H, W)`` ``s``.
        shading: ``(B, 1, H, W)`` ``sigma = exp(s)``.
        reflectance: ``(B, 3, H, W)`` ``rho = I / sigma``.
        diagnostics: :class:`ShadingDiagnostics`.
    """

    log_shading: torch.Tensor
    shading: torch.Tensor
    reflectance: torch.Tensor
    diagnostics: ShadingDiagnostics


_MIN_COARSE = 16


@dataclass
class ShadingSystemCache:
    """Terms of Eq. 1 that do not change between the alternations on one image.

    ``S_c`` (patch features), ``S_m`` (proposal similarities) and ``S_l`` (the image) depend
    only on Stage 0 and the input, not on the previous reflectance, so the pipeline builds
    them once and reuses them in every alternation (the weights ``lambda`` are applied
    afterwards, so the tau schedule of §3.4 is unaffected). Only the matting term ``S_p``,
    whose base image is the previous reflectance, is rebuilt. Keep one cache per image
    batch; an entry is reused only when its inputs (same tensors, unmodified) and
    parameters match, otherwise it is rebuilt.

    Attributes:
        terms: name -> (key of the inputs, the unweighted term).
        hits: how many builds were skipped.
    """

    terms: dict[str, tuple[InputKey, QuadraticTerm]] = field(default_factory=dict)
    hits: int = 0


def _coarse_inputs(
    image: torch.Tensor,
    centers: torch.Tensor | None,
    similarity: torch.Tensor | None,
    base: torch.Tensor | None,
    mask: torch.Tensor | None,
    base_sigma: float,
) -> dict[str, torch.Tensor | None]:
    """Every input of the solve at half resolution (2x2 box averages).

    An approximation, used only to warm-start the full-resolution solve.
    """
    h2, w2 = image.shape[-2] // 2, image.shape[-1] // 2

    def down(x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x[..., : 2 * h2, : 2 * w2], 2)

    out: dict[str, torch.Tensor | None] = {"image": down(image)}
    if base is None and base_sigma > 0:
        base = _default_base(image, mask, base_sigma)
    out["base"] = None if base is None else down(base)
    out["similarity"] = None if similarity is None else down(similarity)
    out["mask"] = None
    if mask is not None:
        cm = down(mask.to(image.dtype)) > 0.5
        # keep every image non-empty
        cm = cm | (~cm.flatten(1).any(1)).view(-1, 1, 1, 1)
        out["mask"] = cm
    out["centers"] = None
    if centers is not None:
        c = torch.div(centers, 2, rounding_mode="floor")
        c[..., 0] = c[..., 0].clamp(0, h2 - 1)
        c[..., 1] = c[..., 1].clamp(0, w2 - 1)
        out["centers"] = c
    return out


def _default_base(image: torch.Tensor, mask: torch.Tensor | None, sigma: float) -> torch.Tensor:
    """Gaussian-smoothed image; inside a mask a normalised convolution (outside ignored)."""
    if mask is None:
        return smooth_base(image, sigma)
    m = mask.to(image.dtype)
    num = smooth_base(image * m, sigma)
    den = smooth_base(m, sigma)
    return torch.where(den > 0, num / den.clamp_min(1e-12), image) * m


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def build_shading_system(
    image: torch.Tensor,
    *,
    patch_centers: torch.Tensor | None = None,
    patch_features: torch.Tensor | None = None,
    similarity: torch.Tensor | None = None,
    base_image: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    lambda_g: float = 0.02,
    lambda_m: float = 0.02,
    lambda_l: float = 2.0,
    use_sc: bool = True,
    use_sp: bool = True,
    t_c: float = 1e-4,
    t_b: float = 0.05,
    t_m: float = 0.05,
    matting_eps: float = 1e-5,
    dark_eps: float = 1e-4,
    dark_level: float = 0.0,
    clip_level: float = 0.0,
    base_sigma: float = 1.0,
    lle_k: int = 10,
    lle_reg: float = 1e-3,
    lle_neighbours: str = "knn",
    seed: int = 0,
    cache: ShadingSystemCache | None = None,
) -> tuple[SumQuadratic, dict[str, float]]:
    """Assemble ``Psi`` (Eq. 1) without the anchor; see :func:`solve_shading` for the arguments.

    Returns:
        ``(system, times)``: the weighted sum of the active terms and the seconds per term.
    """
    check_image(image, "image", channels=3, min_side=3)
    given = image  # cache keys refer to the caller's tensors
    # channels-last strides (a permuted HxWx3 array) slow every shifted product down
    image = image.contiguous()
    base_image = None if base_image is None else base_image.contiguous()
    b, _, h, w = image.shape
    dev, dt = image.device, image.dtype
    if mask is not None:
        check_shape(mask, (b, 1, h, w), "mask")
        if mask.dtype != torch.bool:
            raise ShapeError(f"mask must be a bool tensor, got {mask.dtype}")
        if not bool(mask.flatten(1).any(1).all()):
            raise ParameterError("mask is empty for at least one image: nothing to solve")
    for name, lam in (("lambda_g", lambda_g), ("lambda_m", lambda_m), ("lambda_l", lambda_l)):
        if lam < 0:
            raise ParameterError(f"{name} must be >= 0, got {lam}")
    terms: list[tuple[float, QuadraticTerm | None]] = []
    times: dict[str, float] = {}
    stencil = shading_stencil(h, w, device=dev)

    def timed(name: str, lam: float, fn, key: tuple | None = None) -> None:  # noqa: ANN001
        t0 = time.perf_counter()
        hit = cache is not None and key is not None and name in cache.terms
        if hit and cache.terms[name][0] == key:
            term = cache.terms[name][1]
            cache.hits += 1
        else:
            term = fn()
            if cache is not None and key is not None:
                cache.terms[name] = (key, term)
        _sync(dev)
        times[name] = time.perf_counter() - t0
        terms.append((lam, term))

    if use_sc and lambda_g > 0 and (patch_centers is not None or patch_features is not None):
        if patch_centers is None or patch_features is None:
            raise ParameterError("S_c needs both patch_centers and patch_features")
        timed(
            "S_c",
            lambda_g,
            lambda: lle_term(
                patch_centers.to(dev),
                patch_features.to(device=dev, dtype=dt),
                h,
                w,
                k=lle_k,
                reg=lle_reg,
                neighbours=lle_neighbours,
                mask=mask,
                seed=seed,
            ),
            input_key(
                patch_centers,
                patch_features,
                h,
                w,
                lle_k,
                lle_reg,
                lle_neighbours,
                mask,
                seed,
                dt,
                dev,
            ),
        )
    if use_sp and lambda_g > 0:
        if base_image is not None:
            check_image(base_image, "base_image", channels=3, nonnegative=False)
            check_shape(base_image, (b, 3, h, w), "base_image")
        timed(
            "S_p",
            lambda_g,
            lambda: matting_laplacian(
                _default_base(image, mask, base_sigma) if base_image is None else base_image.to(dt),
                eps=matting_eps,
                mask=mask,
            ).as_stencil(),
        )
    if similarity is not None and lambda_m > 0:
        timed(
            "S_m",
            lambda_m,
            lambda: midlevel_term(similarity.to(dt), stencil, t_m, mask),
            input_key(similarity, t_m, mask, dt),
        )
    if lambda_l > 0:
        timed(
            "S_l",
            lambda_l,
            lambda: retinex_term(
                image,
                stencil,
                t_c,
                t_b,
                dark_eps,
                mask,
                confidence=(
                    pixel_confidence(image, dark_level, clip_level)
                    if dark_level > 0 or clip_level > 0
                    else None
                ),
            ),
            input_key(given, t_c, t_b, dark_eps, dark_level, clip_level, mask),
        )
    if not terms:
        raise ParameterError("every shading term is switched off; enable at least one")
    return SumQuadratic(terms), times


def solve_shading(
    image: torch.Tensor,
    *,
    patch_centers: torch.Tensor | None = None,
    patch_features: torch.Tensor | None = None,
    similarity: torch.Tensor | None = None,
    base_image: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    lambda_g: float = 0.02,
    lambda_m: float = 0.02,
    lambda_l: float = 2.0,
    use_sc: bool = True,
    use_sp: bool = True,
    t_c: float = 1e-4,
    t_b: float = 0.05,
    t_m: float = 0.05,
    matting_eps: float = 1e-5,
    dark_eps: float = 1e-4,
    dark_level: float = 0.0,
    clip_level: float = 0.0,
    base_sigma: float = 1.0,
    lle_k: int = 10,
    lle_reg: float = 1e-3,
    lle_neighbours: str = "knn",
    seed: int = 0,
    anchor: float = 1e-8,
    x0: torch.Tensor | None = None,
    tol: float = 1e-4,
    max_iter: int = 300,
    warn: bool = True,
    levels: int = 5,
    coarse_max_iter: int | None = None,
    cache: ShadingSystemCache | None = None,
) -> ShadingResult:
    """Solve the shading energy of Eq. 1 for ``s = log sigma``; ``rho = I / sigma``.

    Args:
        image: ``(B, 3, H, W)`` linear RGB, ``>= 0``.
        patch_centers: ``(P, 2)`` or ``(B, P, 2)`` integer ``(y, x)`` patch centres (``S_c``).
        patch_features: ``(B, P, D)`` patch features ``f_b`` (or mean RGB for strategies
            p1/p2); ``S_c`` is off when centres/features are ``None``.
        similarity: ``(B, 4, H, W)`` proposal similarities ``<g_i, g_j>`` on the 3x3 stencil
            (:func:`~torchiid.priors.shading_terms.shading_stencil`); ``S_m`` is off when
            ``None``.
        base_image: ``(B, 3, H, W)`` linear RGB base of the matting Laplacian ``S_p`` (the
            previous reflectance); ``None`` uses the Gaussian-smoothed image (``base_sigma``).
        mask: optional ``(B, 1, H, W)`` bool region to decompose (see the module notes).
        lambda_g: weight of ``S_c + S_p`` (paper 0.02); 0 turns both off.
        lambda_m: weight of ``S_m`` (paper 0.02).
        lambda_l: weight of ``S_l`` (paper 2).
        use_sc: switch for ``S_c``.
        use_sp: switch for ``S_p``.
        t_c: chromaticity deviation of ``S_l`` (paper 1e-4, nearly binary).
        t_b: dark-pixel deviation of ``S_l`` (paper 0.05).
        t_m: deviation of ``S_m`` (paper 0.05).
        matting_eps: Levin's epsilon (1e-5).
        dark_eps: floor of intensities before logs; ``rho`` uses ``I`` unclamped.
        dark_level: with ``clip_level``, the pixel confidence of ``S_l``
            (:func:`~torchiid.priors.shading_terms.pixel_confidence`): dark and clipped
            pixels get smooth shading instead of noise. Both 0 (default here): off.
        clip_level: see ``dark_level``.
        base_sigma: Gaussian sigma (px) of the default base image.
        lle_k: LLE neighbours (10).
        lle_reg: LLE Gram regulariser (1e-3).
        lle_neighbours: ``"knn"`` or ``"random"`` (paper Table 2).
        seed: seed of random LLE neighbours.
        anchor: anchor weight relative to the mean diagonal of ``Psi``.
        x0: ``(B, 1, H, W)`` warm start of ``s`` (e.g. the previous iteration's).
        tol: PCG relative-residual tolerance.
        max_iter: PCG iteration cap.
        warn: emit ``ConvergenceWarning`` when ``tol`` is missed.
        levels: coarse-to-fine levels. With ``levels > 1`` (and no ``x0``) the problem is
            first solved on a 2x box-downsampled copy of every input (recursively), and the
            bilinearly upsampled coarse ``s`` warm-starts the full-resolution solve
            ("cascadic" CG). The answer is the full-resolution minimiser either way; only the
            iteration count changes.
        coarse_max_iter: PCG iteration cap on the coarse levels (default ``max_iter``).
        cache: a :class:`ShadingSystemCache` kept across the alternations on one image:
            ``S_c``, ``S_m`` and ``S_l`` are then built once (same result, less time).

    Returns:
        :class:`ShadingResult`.

    Raises:
        ShapeError, ImageError, ParameterError: bad inputs (NaN, shapes, empty mask, no term).

    Shape:
        image ``(B, 3, H, W)`` -> log_shading, shading ``(B, 1, H, W)``;
        reflectance ``(B, 3, H, W)``.
    """
    if anchor <= 0:
        raise ParameterError(f"anchor must be > 0, got {anchor}")
    system, times = build_shading_system(
        image, patch_centers=patch_centers, patch_features=patch_features,
        similarity=similarity, base_image=base_image, mask=mask, lambda_g=lambda_g,
        lambda_m=lambda_m, lambda_l=lambda_l, use_sc=use_sc, use_sp=use_sp, t_c=t_c, t_b=t_b,
        t_m=t_m, matting_eps=matting_eps, dark_eps=dark_eps, dark_level=dark_level,
        clip_level=clip_level, base_sigma=base_sigma, lle_k=lle_k, lle_reg=lle_reg,
        lle_neighbours=lle_neighbours, seed=seed, cache=cache,
    )  # fmt: skip
    image = image.contiguous()
    b, _, h, w = image.shape
    dev, dt = image.device, image.dtype
    m = torch.ones(b, 1, h, w, dtype=dt, device=dev) if mask is None else mask.to(dt)
    area = m.flatten(1).sum(1).view(b, 1, 1, 1)
    logp = intensity(image, dark_eps).log()
    target = (logp * m).flatten(1).sum(1).view(b, 1, 1, 1) / area
    diag = system.diagonal() * m
    alpha = anchor * diag.flatten(1).sum(1).view(b, 1, 1, 1) / area
    alpha = torch.where(alpha > 0, alpha, torch.full_like(alpha, anchor))
    rhs = (system.rhs() + alpha * target) * m
    pinned = 1 - m

    extra = alpha * m + pinned

    def matvec(x: torch.Tensor) -> torch.Tensor:
        if mask is None:
            return system.matvec(x).addcmul_(extra, x)
        return system.matvec(m * x).mul_(m).addcmul_(extra, x)

    precond = 1 / (diag + alpha * m + pinned)
    if x0 is None and levels > 1 and min(h, w) >= 2 * _MIN_COARSE:
        coarse = _coarse_inputs(image, patch_centers, similarity, base_image, mask, base_sigma)
        sub = solve_shading(
            coarse["image"], patch_centers=coarse["centers"], patch_features=patch_features,
            similarity=coarse["similarity"], base_image=coarse["base"], mask=coarse["mask"],
            lambda_g=lambda_g, lambda_m=lambda_m, lambda_l=lambda_l, use_sc=use_sc,
            use_sp=use_sp, t_c=t_c, t_b=t_b, t_m=t_m, matting_eps=matting_eps,
            dark_eps=dark_eps, dark_level=dark_level, clip_level=clip_level,
            base_sigma=base_sigma / 2, lle_k=lle_k, lle_reg=lle_reg,
            lle_neighbours=lle_neighbours, seed=seed, anchor=anchor, tol=tol,
            max_iter=max_iter if coarse_max_iter is None else coarse_max_iter, warn=False,
            levels=levels - 1, coarse_max_iter=coarse_max_iter,
        )  # fmt: skip
        x0 = F.interpolate(sub.log_shading, size=(h, w), mode="bilinear", align_corners=False)
        times["coarse"] = sum(sub.diagnostics.times.values())
    if x0 is None:
        start = target * m
    else:
        check_shape(x0, (b, 1, h, w), "x0")
        check_finite(x0, "x0")
        start = x0.to(dt) * m
    t0 = time.perf_counter()
    res = pcg(matvec, rhs, x0=start, precond=precond, tol=tol, max_iter=max_iter, warn=False)
    _sync(dev)
    times["solve"] = time.perf_counter() - t0
    s = res.x * m
    s = s + (target - (s * m).flatten(1).sum(1).view(b, 1, 1, 1) / area) * m
    if warn and not res.converged:
        warnings.warn(
            f"shading PCG stopped after {res.iterations} iterations with relative residual "
            f"{float(res.residual.max()):.3g} > tol {tol:g}; raise max_iter or warm-start",
            ConvergenceWarning,
            stacklevel=2,
        )
    logger.debug("shading solve: %d iterations, residual %s", res.iterations, res.residual)
    # where the shading underflows (a solve pulled by dark pixels) rho = I / sigma would
    # overflow; sigma >= dark_eps^2 keeps rho finite (<= 1 / dark_eps^2 for I <= 1)
    shading = torch.exp(s).clamp_min(dark_eps * dark_eps)
    reflectance = image / shading
    names = tuple(k for k in times if k not in ("solve", "coarse"))
    diagnostics = ShadingDiagnostics(
        iterations=res.iterations, residual=res.residual, converged=res.converged,
        times=times, terms=names,
    )  # fmt: skip
    return ShadingResult(s, shading, reflectance, diagnostics)
