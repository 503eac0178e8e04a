"""Stage 1: the L2 shading solve (paper §3.2, Eqs. 1-5).

Minimises ``Psi(s) = lambda_c S_c + lambda_p S_p + lambda_m S_m + lambda_l S_l`` (the paper's
``lambda_g`` weighs both ``S_c`` and ``S_p``), plus ``lambda_s S_s`` (plain smoothness, not in
the paper) when on, over the log-shading ``s = log sigma`` of a batch of **linear RGB** images,
as one block-diagonal sparse SPD system solved by batched Jacobi-preconditioned CG
(:func:`torchiid.solvers.pcg.pcg`). The stage takes its tensors, weights and options as the three
objects of :mod:`torchiid.stages.config`; :func:`build_shading_system` is the one place the
priors are built.

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

Speed. The products never touch a sparse matrix: ``S_l``, ``S_m`` and ``S_s`` are 3x3 stencils,
``S_p`` is converted once to an equivalent signed 5x5 stencil
(:meth:`MattingQuadratic.as_stencil`), and they merge into one 12-offset shifted product;
``S_c`` is a small sparse product.
Without a warm start, ``levels > 1`` first solves 2x-downsampled copies of the problem and
upsamples their solution as the initial guess (cascadic CG): the Jacobi-PCG iteration count on
these near-binary, strongly varying weights is dominated by smooth, low-frequency error that the
coarse levels remove cheaply. The assembled torch sparse matrices (``to_sparse()`` of every
term) are the tested reference.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from torchiid.core.cache import InputKey, input_key
from torchiid.core.check import check_finite, check_image, check_shape
from torchiid.core.exceptions import ConvergenceWarning, ParameterError, ShapeError
from torchiid.priors.lle import LLENeighbourhood, lle_term
from torchiid.priors.matting import matting_stencil, smooth_base
from torchiid.priors.quadratic import QuadraticTerm, SumQuadratic
from torchiid.priors.shading_terms import (
    intensity,
    midlevel_term,
    pixel_confidence,
    retinex_term,
    shading_stencil,
    smoothness_term,
)
from torchiid.solvers.multigrid import AMGPreconditioner, GalerkinMultigrid
from torchiid.solvers.pcg import PCGResult, pcg
from torchiid.stages.config import ShadingOptions, ShadingProblem, ShadingWeights

_MULTIGRID_BUDGET = 100
"""PCG iterations a multigrid preconditioner gets before the solve goes on with Jacobi (it
converges in 10–30 on photographs; far more means it stagnates)."""

__all__ = [
    "matting_base",
    "AnchoredSystem",
    "anchored_system",
    "ShadingDiagnostics",
    "ShadingSystem",
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
        times: seconds spent building each term (``"S_c"``, ``"S_p"``, ``"S_m"``, ``"S_l"``,
            ``"S_s"``), in the coarse-to-fine warm start (``"coarse"``, all coarser levels) and
            in the full-resolution PCG (``"solve"``).
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


@dataclass(frozen=True)
class ShadingSystem:
    """Eq. 1's energy as built by :func:`build_shading_system`.

    Attributes:
        total: the weighted sum of the active priors (the solver's operator; stencil terms
            merged into one shifted product).
        terms: name (``"S_c"``, ``"S_p"``, ``"S_m"``, ``"S_l"``, ``"S_s"``) -> ``(weight, term)``
            of every active prior, unweighted and unmerged.
        times: seconds spent building each term.
    """

    total: SumQuadratic
    terms: dict[str, tuple[float, QuadraticTerm]]
    times: dict[str, float]


@dataclass
class ShadingSystemCache:
    """Terms of Eq. 1 that do not change between the alternations on one image.

    ``S_c`` (patch features), ``S_m`` (proposal similarities), ``S_l`` (the image) and ``S_s``
    (the image size and mask) depend only on Stage 0 and the input, not on the previous
    reflectance, so the pipeline builds them once and reuses them in every alternation (the
    weights ``lambda`` are applied afterwards, so the tau schedule of §3.4 is unaffected).
    Only the matting term ``S_p``, whose base image is the previous reflectance, is rebuilt.
    Keep one cache per image batch; an entry is reused only when its inputs (same tensors,
    unmodified) and parameters match, otherwise it is rebuilt.

    Attributes:
        terms: name -> (key of the inputs, the unweighted term).
        hits: how many builds were skipped.
        preconditioner: a multigrid hierarchy built for an earlier alternation, reused as
            long as it keeps its iteration count (see ``ShadingOptions.preconditioner``).
        fresh_iterations: the PCG iterations it needed on the system it was built for.
        neighbourhood: ``S_c``'s neighbours and LLE weights, shared with the coarser levels
            of a coarse-to-fine solve (which build ``S_c`` on their own grids from the same
            features).
    """

    terms: dict[str, tuple[InputKey, QuadraticTerm]] = field(default_factory=dict)
    hits: int = 0
    preconditioner: object | None = None
    fresh_iterations: int = 0
    neighbourhood: LLENeighbourhood = field(default_factory=LLENeighbourhood)


def _coarse_problem(problem: ShadingProblem, base_sigma: float, base_mix: float) -> ShadingProblem:
    """Every input of the solve at half resolution (2x2 box averages).

    An approximation, used only to warm-start the full-resolution solve. Its ``base_image`` is
    the full-resolution matting base itself, downsampled (solve it with ``base_mix = 1``, so it
    is not mixed again).
    """
    image, mask = problem.image, problem.mask
    h2, w2 = image.shape[-2] // 2, image.shape[-1] // 2

    def down(x: torch.Tensor) -> torch.Tensor:
        return F.avg_pool2d(x[..., : 2 * h2, : 2 * w2], 2)

    base = problem.base_image
    if base is None and base_sigma > 0:
        base = _default_base(image, mask, base_sigma)
    elif base is not None:
        base = matting_base(image, base.to(image.dtype), mask, base_sigma, base_mix)
    coarse_mask = None
    if mask is not None:
        cm = down(mask.to(image.dtype)) > 0.5
        # keep every image non-empty
        coarse_mask = cm | (~cm.flatten(1).any(1)).view(-1, 1, 1, 1)
    centers = problem.patch_centers
    if centers is not None:
        centers = torch.div(centers, 2, rounding_mode="floor")
        centers[..., 0] = centers[..., 0].clamp(0, h2 - 1)
        centers[..., 1] = centers[..., 1].clamp(0, w2 - 1)
    return ShadingProblem(
        image=down(image),
        patch_centers=centers,
        patch_features=problem.patch_features,
        similarity=None if problem.similarity is None else down(problem.similarity),
        base_image=None if base is None else down(base),
        mask=coarse_mask,
    )


def matting_base(
    image: torch.Tensor,
    reflectance: torch.Tensor,
    mask: torch.Tensor | None,
    sigma: float,
    mix: float,
) -> torch.Tensor:
    """The base image of ``S_p`` in alternations 2..k: ``R^mix · I_σ^(1 − mix)`` per channel.

    The paper takes the previous reflectance ``R`` (``mix = 1``). Where ``R`` is flat the
    matting Laplacian then asks for locally constant shading, so the shading detail the
    previous alternation found (relief, bumps: the Retinex term ties them to the
    shading) is pushed into the reflectance at the next one. Mixing in the Gaussian-smoothed
    image ``I_σ`` (the first alternation's base), as a weighted geometric mean, keeps a damped
    copy of the shading's edges in the base (``R^β I^(1−β) ≈ R S^(1−β)``), so the term no
    longer works against them. ``mix = 0``: the smoothed image in every alternation.

    Shape:
        image, reflectance ``(B, 3, H, W)`` (linear), mask ``(B, 1, H, W)`` or ``None``.
    """
    if mix >= 1:
        return reflectance
    smooth = _default_base(image, mask, sigma)
    if mix <= 0:
        return smooth
    # fractional powers need positive bases: black (or, from a caller, negative) values are
    # raised to a floor far below any visible level
    floor = max(1e-8, torch.finfo(image.dtype).tiny)
    return reflectance.clamp_min(floor).pow(mix) * smooth.clamp_min(floor).pow(1.0 - mix)


def _default_base(image: torch.Tensor, mask: torch.Tensor | None, sigma: float) -> torch.Tensor:
    """Gaussian-smoothed image; inside a mask a normalised convolution (outside ignored)."""
    if mask is None:
        return smooth_base(image, sigma)
    m = mask.to(image.dtype)
    num = smooth_base(image * m, sigma)
    den = smooth_base(m, sigma)
    return torch.where(den > 0, num / den.clamp_min(1e-12), image) * m


@dataclass(frozen=True)
class AnchoredSystem:
    """The linear system :func:`solve_shading` hands to PCG (the one place of its formulas).

    Attributes:
        total: ``Psi``, the weighted sum of the priors (without anchor).
        matvec: ``x -> A x`` with ``A = D_m Psi D_m + diag(extra)``.
        rhs: ``(B, 1, H, W)`` right-hand side.
        target: ``(B, 1, 1, 1)`` mean ``log p`` inside the mask (the gauge of ``s``).
        inside: ``(B, 1, H, W)`` float 0/1 mask (ones without a mask).
        area: ``(B, 1, 1, 1)`` pixels inside.
        extra: ``(B, 1, H, W)`` the added diagonal ``alpha m + (1 - m)``.
        jacobi: ``(B, 1, H, W)`` the inverse diagonal of ``A``.
    """

    total: QuadraticTerm
    matvec: Callable[[torch.Tensor], torch.Tensor]
    rhs: torch.Tensor
    target: torch.Tensor
    inside: torch.Tensor
    area: torch.Tensor
    extra: torch.Tensor
    jacobi: torch.Tensor

    @property
    def x0(self) -> torch.Tensor:
        """The cold start: the target mean inside the mask."""
        return self.target * self.inside


def anchored_system(
    total: QuadraticTerm,
    image: torch.Tensor,
    mask: torch.Tensor | None,
    anchor: float,
    dark_eps: float,
) -> AnchoredSystem:
    """Eq. 1's energy made positive definite: the anchor and the pinning of outside pixels.

    Every term annihilates constants, so a tiny anchor ``alpha * sum_i (s_i - t)^2`` over the
    region (``alpha = anchor * mean(diag(Psi))``, ``t`` the mean of ``log p``) fixes the free
    constant; pixels outside ``mask`` are pinned to ``s = 0`` (see the module notes).

    Args:
        total: ``build_shading_system(...).total``.
        image: ``(B, 3, H, W)`` linear RGB.
        mask: ``(B, 1, H, W)`` bool or ``None``.
        anchor: ``options.anchor``.
        dark_eps: ``options.dark_eps``.

    Returns:
        :class:`AnchoredSystem`.
    """
    b, _, h, w = image.shape
    dt, dev = image.dtype, image.device
    m = torch.ones(b, 1, h, w, dtype=dt, device=dev) if mask is None else mask.to(dt)
    area = m.flatten(1).sum(1).view(b, 1, 1, 1)
    target = (intensity(image, dark_eps).log() * m).flatten(1).sum(1).view(b, 1, 1, 1) / area
    diag = total.diagonal() * m
    alpha = anchor * diag.flatten(1).sum(1).view(b, 1, 1, 1) / area
    alpha = torch.where(alpha > 0, alpha, torch.full_like(alpha, anchor))
    rhs = (total.rhs() + alpha * target) * m
    extra = alpha * m + (1 - m)

    def matvec(x: torch.Tensor) -> torch.Tensor:
        if mask is None:
            return total.matvec(x).addcmul_(extra, x)
        return total.matvec(m * x).mul_(m).addcmul_(extra, x)

    return AnchoredSystem(total, matvec, rhs, target, m, area, extra, 1 / (diag + extra))


def _multigrid(kind: str, system: SumQuadratic, extra: torch.Tensor, mask: torch.Tensor | None):
    """The multigrid preconditioner ``kind`` for ``D_m system D_m + diag(extra)``."""
    if kind == "amg":
        if extra.device.type != "cpu":
            raise ParameterError("preconditioner 'amg' (pyamg) runs on the CPU; use 'multigrid'")
        return AMGPreconditioner.from_system(system, extra, mask)
    return GalerkinMultigrid.from_system(system, extra, mask)


def _relative_residual(
    matvec: Callable[[torch.Tensor], torch.Tensor], rhs: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """``||rhs - A x|| / ||rhs||`` per image, ``(B,)``; NaN (an overflowed ``x``) as ``inf``."""
    r = (rhs - matvec(x)).flatten(1).norm(dim=1) / rhs.flatten(1).norm(dim=1).clamp_min(1e-30)
    return torch.nan_to_num(r, nan=math.inf)


def _solve_in_float64(
    problem: ShadingProblem, weights: ShadingWeights, options: ShadingOptions, x0: torch.Tensor
) -> PCGResult | None:
    """The same shading solve with every tensor in float64, from ``x0``.

    Returns the result in ``x0``'s dtype (its residual as float64 measures it: the float32
    product is what cannot resolve it), or ``None`` where float64 is not available (MPS).
    """
    if problem.image.device.type == "mps":
        return None
    changes = {
        f.name: v.to(torch.float64)
        for f in dataclasses.fields(problem)
        if torch.is_tensor(v := getattr(problem, f.name)) and v.is_floating_point()
    }
    sub = solve_shading(
        dataclasses.replace(problem, **changes),
        weights,
        options.replace(warm_max_iter=0, warn=False),
        x0=x0.to(torch.float64),
    )
    d = sub.diagnostics
    logger.info("shading solve redone in float64: %d iterations, residual %s",
                d.iterations, d.residual.tolist())  # fmt: skip
    b = x0.shape[0]
    return PCGResult(
        x=sub.log_shading.to(x0.dtype),
        iterations=d.iterations,
        residual=d.residual.to(x0.dtype),
        converged=d.converged,
        item_iterations=torch.full((b,), d.iterations, dtype=torch.long, device=x0.device),
    )


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def build_shading_system(
    problem: ShadingProblem,
    weights: ShadingWeights,
    options: ShadingOptions,
    cache: ShadingSystemCache | None = None,
) -> ShadingSystem:
    """Assemble ``Psi`` (Eq. 1) without the anchor: the one place the shading priors are built.

    Args:
        problem: the tensors (:class:`~torchiid.stages.config.ShadingProblem`).
        weights: one weight per prior, 0 is off (``S_c`` also needs patch centres and
            features, ``S_m`` the similarities; ``S_p`` without a base image uses the
            Gaussian-smoothed image).
        options: the priors' constants.
        cache: a :class:`ShadingSystemCache` kept across the alternations on one image.

    Returns:
        :class:`ShadingSystem`.
    """
    image = problem.image
    check_image(image, "image", channels=3, min_side=3)
    given = image  # cache keys refer to the caller's tensors
    # channels-last strides (a permuted HxWx3 array) slow every shifted product down
    image = image.contiguous()
    base_image = None if problem.base_image is None else problem.base_image.contiguous()
    mask, o = problem.mask, options
    b, _, h, w = image.shape
    dev, dt = image.device, image.dtype
    if mask is not None:
        check_shape(mask, (b, 1, h, w), "mask")
        if mask.dtype != torch.bool:
            raise ShapeError(f"mask must be a bool tensor, got {mask.dtype}")
        if not bool(mask.flatten(1).any(1).all()):
            raise ParameterError("mask is empty for at least one image: nothing to solve")
    terms: dict[str, tuple[float, QuadraticTerm]] = {}
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
        terms[name] = (lam, term)

    centers, feats = problem.patch_centers, problem.patch_features
    if weights.lambda_c > 0 and (centers is not None or feats is not None):
        if centers is None or feats is None:
            raise ParameterError("S_c needs both patch_centers and patch_features")
        timed(
            "S_c",
            weights.lambda_c,
            lambda: lle_term(
                centers.to(dev),
                feats.to(device=dev, dtype=dt),
                h,
                w,
                k=o.lle_k,
                reg=o.lle_reg,
                neighbours=o.lle_neighbours,
                mask=mask,
                seed=o.seed,
                reuse=None if cache is None else cache.neighbourhood,
            ),
            input_key(
                centers, feats, h, w, o.lle_k, o.lle_reg, o.lle_neighbours, mask, o.seed, dt, dev
            ),
        )
    if weights.lambda_p > 0:
        if base_image is not None:
            check_image(base_image, "base_image", channels=3, nonnegative=False)
            check_shape(base_image, (b, 3, h, w), "base_image")
        timed(
            "S_p",
            weights.lambda_p,
            lambda: matting_stencil(
                _default_base(image, mask, o.base_sigma)
                if base_image is None
                else matting_base(image, base_image.to(dt), mask, o.base_sigma, o.base_mix),
                eps=o.matting_eps,
                mask=mask,
            ),
        )
    if problem.similarity is not None and weights.lambda_m > 0:
        sim = problem.similarity
        timed(
            "S_m",
            weights.lambda_m,
            lambda: midlevel_term(sim.to(dt), stencil, o.t_m, mask),
            input_key(sim, o.t_m, mask, dt),
        )
    if weights.lambda_l > 0:
        confident = o.dark_level > 0 or o.clip_level > 0
        timed(
            "S_l",
            weights.lambda_l,
            lambda: retinex_term(
                image,
                stencil,
                o.t_c,
                o.t_b,
                o.dark_eps,
                mask,
                confidence=(
                    pixel_confidence(image, o.dark_level, o.clip_level) if confident else None
                ),
                t_i=o.t_i,
                t_e=o.t_e,
                t_d=o.t_d,
                t_h=o.t_h,
            ),
            input_key(
                given,
                o.t_c,
                o.t_b,
                o.t_i,
                o.t_e,
                o.t_d,
                o.t_h,
                o.dark_eps,
                o.dark_level,
                o.clip_level,
                mask,
            ),
        )
    if weights.lambda_s > 0:
        timed(
            "S_s",
            weights.lambda_s,
            lambda: smoothness_term(stencil, b, mask, dt),
            input_key(b, h, w, mask, dt, dev),
        )
    if not terms:
        raise ParameterError("every shading term is switched off; enable at least one")
    return ShadingSystem(SumQuadratic(list(terms.values())), terms, times)


def solve_shading(
    problem: ShadingProblem,
    weights: ShadingWeights,
    options: ShadingOptions,
    *,
    x0: torch.Tensor | None = None,
    cache: ShadingSystemCache | None = None,
) -> ShadingResult:
    """Solve the shading energy of Eq. 1 for ``s = log sigma``; ``rho = I / sigma``.

    Args:
        problem: the tensors (:class:`~torchiid.stages.config.ShadingProblem`): the image,
            Stage 0's patch features and proposal similarities, the matting base image
            (the previous reflectance) and the mask (see the module notes).
        weights: :class:`~torchiid.stages.config.ShadingWeights`, 0 switches a prior off.
        options: :class:`~torchiid.stages.config.ShadingOptions`: the priors' constants and
            the PCG settings.
        x0: ``(B, 1, H, W)`` warm start of ``s`` (e.g. the previous iteration's); the solve
            then runs at most ``options.warm_max_iter`` iterations (0: ``max_iter``). Without
            it and with ``options.levels > 1`` the problem is first solved on a 2x
            box-downsampled copy of every input (recursively) and the bilinearly upsampled
            coarse ``s`` warm-starts the full-resolution solve ("cascadic" CG). The answer
            is the full-resolution minimiser either way; only the iteration count changes.
        cache: a :class:`ShadingSystemCache` kept across the alternations on one image:
            ``S_c``, ``S_m``, ``S_l`` and ``S_s`` are then built once (same result, less
            time).

    Returns:
        :class:`ShadingResult`.

    Raises:
        ShapeError, ImageError, ParameterError: bad inputs (NaN, shapes, empty mask, no term).

    Shape:
        image ``(B, 3, H, W)`` -> log_shading, shading ``(B, 1, H, W)``;
        reflectance ``(B, 3, H, W)``.
    """
    o = options
    # a cache for this call alone when none is given: the coarse levels share its S_c
    # neighbourhood (everything else in it starts empty, as without one)
    cache = ShadingSystemCache() if cache is None else cache
    built = build_shading_system(problem, weights, options, cache)
    system, times = built.total, dict(built.times)
    image, mask = problem.image.contiguous(), problem.mask
    b, _, h, w = image.shape
    dev, dt = image.device, image.dtype
    anchored = anchored_system(system, image, mask, o.anchor, o.dark_eps)
    matvec, rhs, extra = anchored.matvec, anchored.rhs, anchored.extra
    m, area, target = anchored.inside, anchored.area, anchored.target
    precond = anchored.jacobi
    max_iter = o.max_iter
    fresh = False
    if o.preconditioner != "jacobi":
        precond = cache.preconditioner
        if precond is None:
            t0 = time.perf_counter()
            precond = _multigrid(o.preconditioner, system, extra, mask)
            times["preconditioner"] = time.perf_counter() - t0
            fresh = True
    if x0 is not None:
        max_iter = o.warm_max_iter or o.max_iter
    elif o.preconditioner == "jacobi" and o.levels > 1 and min(h, w) >= 2 * _MIN_COARSE:
        sub = solve_shading(
            _coarse_problem(problem, o.base_sigma, o.base_mix),
            weights,
            o.replace(base_sigma=o.base_sigma / 2, base_mix=1.0, levels=o.levels - 1, warn=False),
            cache=ShadingSystemCache(neighbourhood=cache.neighbourhood),
        )
        x0 = F.interpolate(sub.log_shading, size=(h, w), mode="bilinear", align_corners=False)
        times["coarse"] = sum(sub.diagnostics.times.values())
    if x0 is None:
        start = target * m
    else:
        check_shape(x0, (b, 1, h, w), "x0")
        check_finite(x0, "x0")
        start = x0.to(dt) * m
    t0 = time.perf_counter()
    reused = o.preconditioner != "jacobi" and not fresh
    budget = min(max_iter, 2 * cache.fresh_iterations + 5) if reused else max_iter
    if o.preconditioner != "jacobi":
        budget = min(budget, _MULTIGRID_BUDGET)
    res = pcg(matvec, rhs, x0=start, precond=precond, tol=o.tol, max_iter=budget, warn=False)
    if reused and not res.converged and res.iterations < max_iter:
        # the system drifted from the one the hierarchy was built for: rebuild it and go on
        # from the current iterate in this same solve
        t1 = time.perf_counter()
        precond, fresh = _multigrid(o.preconditioner, system, extra, mask), True
        times["preconditioner"] = time.perf_counter() - t1
        more = pcg(
            matvec, rhs, x0=res.x, precond=precond, tol=o.tol,
            max_iter=min(max_iter - res.iterations, _MULTIGRID_BUDGET), warn=False,
        )  # fmt: skip
        res = dataclasses.replace(more, iterations=res.iterations + more.iterations)
    res_start = None  # the start's relative residual, once computed
    if not res.converged and o.preconditioner != "jacobi" and dt == torch.float32:
        # the solve to tolerance failed in float32: the products of a badly scaled system
        # (near-binary Retinex weights, a matting base that a converged L1 stage made almost
        # flat) lose more than the tolerance to round-off, so neither multigrid nor Jacobi gets
        # there (MIT's box, alternation 4 of the converged preset: multigrid, then 1382 Jacobi
        # iterations ending at a relative residual of 0.92). The same system in float64 takes
        # 12 multigrid iterations; redo it there, from the better iterate
        t1 = time.perf_counter()
        res_start = _relative_residual(matvec, rhs, start)
        better = _relative_residual(matvec, rhs, res.x) <= res_start
        restart = torch.where(better.view(-1, 1, 1, 1), res.x, start)
        more = _solve_in_float64(problem, weights, o, restart)
        if more is not None:
            res = dataclasses.replace(more, iterations=res.iterations + more.iterations)
            times["float64"] = time.perf_counter() - t1
    if o.preconditioner != "jacobi" and not res.converged and res.iterations < max_iter:
        # a multigrid that stagnates (round-off on a very ill-conditioned system, e.g. the
        # matting Laplacian of an exactly piecewise-constant base image) or breaks down, where
        # float64 did not help or is not available: finish with the always-SPD Jacobi
        # preconditioner from the current iterate
        more = pcg(
            matvec, rhs, x0=res.x, precond=anchored.jacobi, tol=o.tol,
            max_iter=max_iter - res.iterations, warn=False,
        )  # fmt: skip
        res = dataclasses.replace(more, iterations=res.iterations + more.iterations)
    if not res.converged:
        # a solve that broke down (the float32 operator not positive definite on a near-flat
        # matting base, seen in late alternations of converged runs) can end farther from the
        # solution than where it started: keep the start for those images, never a worse answer
        res0 = res_start if res_start is not None else _relative_residual(matvec, rhs, start)
        worse = ~(res.residual <= res0)  # NaN counts as worse
        if bool(worse.any()):
            logger.info(
                "shading solve ended with relative residual %s above its start's %s; "
                "keeping the start",
                res.residual.tolist(),
                res0.tolist(),
            )
            x = torch.where(worse.view(-1, 1, 1, 1), start, res.x)
            res = dataclasses.replace(res, x=x, residual=torch.where(worse, res0, res.residual))
    _sync(dev)
    times["solve"] = time.perf_counter() - t0
    if fresh:
        cache.preconditioner, cache.fresh_iterations = precond, res.iterations
    # a row the priors barely constrain (every pair cut) can make an early-stopped,
    # Jacobi-preconditioned solve overflow in float32; keep s finite and within 1e±8 of the
    # light's level (beyond any real shading) so the next alternation and R = I / S stay defined
    bound = -2.0 * math.log(o.dark_eps)
    s = torch.nan_to_num(res.x, nan=0.0, posinf=bound, neginf=-bound).clamp_(-bound, bound) * m
    s = s + (target - (s * m).flatten(1).sum(1).view(b, 1, 1, 1) / area) * m
    if o.warn and not res.converged:
        warnings.warn(
            f"shading PCG stopped after {res.iterations} iterations with relative residual "
            f"{float(res.residual.max()):.3g} > tol {o.tol:g}; raise max_iter or warm-start",
            ConvergenceWarning,
            stacklevel=2,
        )
    logger.debug("shading solve: %d iterations, residual %s", res.iterations, res.residual)
    # where the shading underflows (a solve pulled by dark pixels) rho = I / sigma would
    # overflow; sigma >= dark_eps^2 keeps rho finite (<= 1 / dark_eps^2 for I <= 1)
    shading = torch.exp(s).clamp_min(o.dark_eps * o.dark_eps)
    reflectance = image / shading
    names = tuple(k for k in times if k not in ("solve", "coarse", "preconditioner", "float64"))
    diagnostics = ShadingDiagnostics(
        iterations=res.iterations, residual=res.residual, converged=res.converged,
        times=times, terms=names,
    )  # fmt: skip
    return ShadingResult(s, shading, reflectance, diagnostics)
