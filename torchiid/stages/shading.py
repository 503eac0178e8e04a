"""Stage 1: the L2 shading solve (paper §3.2, Eqs. 1-5).

Minimises ``Psi(s) = lambda_c S_c + lambda_p S_p + lambda_m S_m + lambda_l S_l`` (the paper's
``lambda_g`` weighs both ``S_c`` and ``S_p``), plus ``lambda_s S_s`` (plain smoothness, not in
the paper) when on, over the log-shading ``s = log sigma`` of a batch of **linear RGB** images,
as one block-diagonal sparse SPD system solved by batched Jacobi-preconditioned CG
(:func:`torchiid.solvers.pcg.pcg`). The stage takes its tensors
(:class:`~torchiid.stages.config.ShadingProblem`) and its parameters
(:class:`~torchiid.params.ShadingParameters`); :func:`build_shading_system`
(:mod:`torchiid.stages.shading_system`) is the one place the priors are built.

Masks. With ``mask`` every term drops the pairs, windows and rows that touch a pixel outside;
outside pixels are pinned to ``s = 0`` (``sigma = 1``, ``rho = I``) and do not enter the solve,
so the masked object is decomposed by itself.
The anchor and the products: :mod:`torchiid.stages.shading_system`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from torchiid.core.cache import input_key
from torchiid.core.check import check_finite, check_shape
from torchiid.core.exceptions import ConvergenceWarning, ParameterError
from torchiid.params import ShadingParameters
from torchiid.priors.quadratic import SumQuadratic
from torchiid.priors.texture import texture_confidence
from torchiid.solvers.multigrid import AMGPreconditioner, GalerkinMultigrid
from torchiid.solvers.pcg import PCGResult, pcg
from torchiid.stages.config import ShadingProblem, check_group
from torchiid.stages.shading_system import (
    AnchoredSystem,
    ShadingSystem,
    ShadingSystemCache,
    anchored_system,
    assemble_shading_system,
    build_shading_system,
    coarse_problem,
    matting_base,
    sync,
)

_MULTIGRID_BUDGET = 100
"""PCG iterations a multigrid preconditioner gets before the solve goes on with Jacobi (it
converges in 10–30 on photographs; far more means it stagnates)."""

_MIN_COARSE = 16  # smallest side of a coarse level of the coarse-to-fine start

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


def solve_shading(
    problem: ShadingProblem,
    shading: ShadingParameters,
    *,
    x0: torch.Tensor | None = None,
    cache: ShadingSystemCache | None = None,
    seed: int = 0,
    warn: bool = True,
) -> ShadingResult:
    """Solve the shading energy of Eq. 1 for ``s = log sigma``; ``rho = I / sigma``.

    Args:
        problem: the tensors (:class:`~torchiid.stages.config.ShadingProblem`): the image,
            Stage 0's patch features and proposal similarities, the matting base image
            (the previous reflectance) and the mask (see the module notes).
        shading: the stage's parameters (:class:`~torchiid.params.ShadingParameters`, e.g.
            ``params.alternation(k)[0]``): the priors' weights (0 or a switch turns a prior
            off), their constants and the PCG settings.
        x0: ``(B, 1, H, W)`` warm start of ``s`` (e.g. the previous iteration's); the solve
            then runs at most ``warm_cg_max_iter`` iterations (0: ``cg_max_iter``). Without
            it and with ``coarse_levels > 1`` the problem is first solved on a 2x
            box-downsampled copy of every input (recursively) and the bilinearly upsampled
            coarse ``s`` warm-starts the full-resolution solve ("cascadic" CG). The answer
            is the full-resolution minimiser either way; only the iteration count changes.
        cache: a :class:`ShadingSystemCache` kept across the alternations on one image:
            ``S_c``, ``S_m``, ``S_l`` and ``S_s`` are then built once (same result, less
            time).
        seed: seed of random LLE neighbours (``Parameters.seed``).
        warn: emit a ``ConvergenceWarning`` when the solve stops at its cap
            (:func:`~torchiid.decompose` reports instead).

    Returns:
        :class:`ShadingResult`.

    Raises:
        ShapeError, ImageError, ParameterError: bad inputs (NaN, shapes, empty mask, no term).

    Shape:
        image ``(B, 3, H, W)`` -> log_shading, shading ``(B, 1, H, W)``;
        reflectance ``(B, 3, H, W)``.
    """
    group = check_group("solve_shading", shading, ShadingParameters, "shading")
    return _solve(_Task(problem, group, group.weights(), seed), x0=x0, cache=cache, warn=warn)


@dataclass(frozen=True)
class _Task:
    """One system to solve: its tensors, parameters, each prior's weight and the LLE seed."""

    problem: ShadingProblem
    o: ShadingParameters
    weights: Mapping[str, float]
    seed: int


def _solve(
    task: _Task, *, x0: torch.Tensor | None, cache: ShadingSystemCache | None, warn: bool
) -> ShadingResult:
    """:func:`solve_shading` with each prior's weight given."""
    # a cache for this call alone when none is given: the coarse levels share its S_c
    # neighbourhood (everything else in it starts empty, as without one)
    cache = ShadingSystemCache() if cache is None else cache
    problem, o = task.problem, task.o
    if problem.texture is None and o.t_x > 0 and task.weights.get("S_l", 0.0) > 0:
        # S_l's texture marks once at this size: the coarse levels take them area-averaged
        key = input_key(problem.image, o.t_x, o.t_xc, o.dark_eps, problem.mask)
        if cache.texture is None or cache.texture[0] != key:
            made = texture_confidence(problem.image, o.t_x, problem.mask, o.dark_eps, t_xc=o.t_xc)
            cache.texture = (key, made)
        problem = problem.replace(texture=cache.texture[1])
        task = dataclasses.replace(task, problem=problem)
    built = assemble_shading_system(problem, o, task.weights, cache, task.seed)
    times = dict(built.times)
    image, mask = problem.image.contiguous(), problem.mask
    anchored = anchored_system(built.total, image, mask, o.anchor, o.dark_eps)
    precond, fresh = _preconditioner(o, built.total, anchored.extra, mask, cache, times)
    if x0 is not None:
        max_iter = o.warm_cg_max_iter or o.cg_max_iter
    else:
        max_iter = o.cg_max_iter
        x0 = _coarse_start(task, cache, times)
    start = _start(x0, anchored, image)
    t0 = time.perf_counter()
    res, precond, fresh = _pcg(
        anchored, start, o, precond, fresh, max_iter, built.total, mask, cache, times
    )
    if not res.converged:
        res = _rescue(res, anchored, start, task, max_iter, times)
    sync(image.device)
    times["solve"] = time.perf_counter() - t0
    if fresh:
        cache.preconditioner, cache.fresh_iterations = precond, res.iterations
    return _result(res, anchored, image, o, times, warn)


def _multigrid(kind: str, system: SumQuadratic, extra: torch.Tensor, mask: torch.Tensor | None):
    """The multigrid preconditioner ``kind`` for ``D_m system D_m + diag(extra)``."""
    if kind == "amg":
        if extra.device.type != "cpu":
            raise ParameterError("preconditioner 'amg' (pyamg) runs on the CPU; use 'multigrid'")
        return AMGPreconditioner.from_system(system, extra, mask)
    return GalerkinMultigrid.from_system(system, extra, mask)


def _preconditioner(
    o: ShadingParameters,
    system: SumQuadratic,
    extra: torch.Tensor,
    mask: torch.Tensor | None,
    cache: ShadingSystemCache,
    times: dict[str, float],
) -> tuple[object | None, bool]:
    """``(multigrid hierarchy, whether built now)``; ``(None, False)`` for Jacobi.

    A hierarchy built in an earlier alternation (kept in the cache) is reused: the system
    changes little from one alternation to the next.
    """
    if o.shading_preconditioner == "jacobi":
        return None, False
    if cache.preconditioner is not None:
        return cache.preconditioner, False
    t0 = time.perf_counter()
    precond = _multigrid(o.shading_preconditioner, system, extra, mask)
    times["preconditioner"] = time.perf_counter() - t0
    return precond, True


def _coarse_start(
    task: _Task, cache: ShadingSystemCache, times: dict[str, float]
) -> torch.Tensor | None:
    """The cold start of a Jacobi solve: the half-size problem's ``s``, upsampled, or ``None``.

    The Jacobi-PCG iteration count on these near-binary weights is dominated by smooth error,
    which the coarse levels remove cheaply; a multigrid preconditioner removes it itself.
    """
    o = task.o
    h, w = task.problem.image.shape[-2:]
    if o.shading_preconditioner != "jacobi" or o.coarse_levels <= 1 or min(h, w) < 2 * _MIN_COARSE:
        return None
    coarse = dataclasses.replace(
        task,
        problem=coarse_problem(task.problem, o.base_sigma, o.base_mix),
        o=o.replace(base_sigma=o.base_sigma / 2, base_mix=1.0, coarse_levels=o.coarse_levels - 1),
    )
    sub = _solve(
        coarse, x0=None, cache=ShadingSystemCache(neighbourhood=cache.neighbourhood), warn=False
    )
    times["coarse"] = sum(sub.diagnostics.times.values())
    return F.interpolate(sub.log_shading, size=(h, w), mode="bilinear", align_corners=False)


def _start(x0: torch.Tensor | None, anchored: AnchoredSystem, image: torch.Tensor) -> torch.Tensor:
    """PCG's first iterate: ``x0`` inside the mask, or the target mean (a cold start)."""
    if x0 is None:
        return anchored.target * anchored.inside
    b, _, h, w = image.shape
    check_shape(x0, (b, 1, h, w), "x0")
    check_finite(x0, "x0")
    return x0.to(image.dtype) * anchored.inside


def _pcg(
    anchored: AnchoredSystem,
    start: torch.Tensor,
    o: ShadingParameters,
    precond: object | None,
    fresh: bool,
    max_iter: int,
    system: SumQuadratic,
    mask: torch.Tensor | None,
    cache: ShadingSystemCache,
    times: dict[str, float],
) -> tuple[PCGResult, object, bool]:
    """PCG from ``start``: ``(result, preconditioner, whether it was built in this solve)``.

    A reused multigrid hierarchy gets twice its fresh iteration count (and 5 more); one that
    needs more no longer fits the system, which has drifted: it is rebuilt and the solve goes
    on from the current iterate.
    """
    matvec, rhs = anchored.matvec, anchored.rhs
    multigrid = o.shading_preconditioner != "jacobi"
    precond = anchored.jacobi if precond is None else precond
    reused = multigrid and not fresh
    budget = min(max_iter, 2 * cache.fresh_iterations + 5) if reused else max_iter
    if multigrid:
        budget = min(budget, _MULTIGRID_BUDGET)
    res = pcg(matvec, rhs, x0=start, precond=precond, tol=o.cg_tol, max_iter=budget, warn=False)
    if reused and not res.converged and res.iterations < max_iter:
        t1 = time.perf_counter()
        precond, fresh = _multigrid(o.shading_preconditioner, system, anchored.extra, mask), True
        times["preconditioner"] = time.perf_counter() - t1
        more = pcg(
            matvec, rhs, x0=res.x, precond=precond, tol=o.cg_tol,
            max_iter=min(max_iter - res.iterations, _MULTIGRID_BUDGET), warn=False,
        )  # fmt: skip
        res = dataclasses.replace(more, iterations=res.iterations + more.iterations)
    return res, precond, fresh


def _rescue(
    res: PCGResult,
    anchored: AnchoredSystem,
    start: torch.Tensor,
    task: _Task,
    max_iter: int,
    times: dict[str, float],
) -> PCGResult:
    """A solve that missed its tolerance: multigrid redone in float64, finished by Jacobi.

    In float32 the products of a badly scaled system (near-binary Retinex weights, a matting
    base that a converged L1 stage made almost flat) lose more than the tolerance to
    round-off; the same system in float64 gets there, from the better of the start and the
    iterate. A multigrid that still stagnates is finished with the always-SPD Jacobi
    preconditioner (Jacobi solves stop at their caps by design). Never worse than the start.
    """
    matvec, rhs = anchored.matvec, anchored.rhs
    res_start = None  # the start's relative residual, once computed
    o = task.o
    multigrid = o.shading_preconditioner != "jacobi"
    if multigrid and task.problem.image.dtype == torch.float32:
        t1 = time.perf_counter()
        res_start = _relative_residual(matvec, rhs, start)
        better = _relative_residual(matvec, rhs, res.x) <= res_start
        restart = torch.where(better.view(-1, 1, 1, 1), res.x, start)
        more = _solve_in_float64(task, restart)
        if more is not None:
            res = dataclasses.replace(more, iterations=res.iterations + more.iterations)
            times["float64"] = time.perf_counter() - t1
    if multigrid and not res.converged and res.iterations < max_iter:
        more = pcg(
            matvec, rhs, x0=res.x, precond=anchored.jacobi, tol=o.cg_tol,
            max_iter=max_iter - res.iterations, warn=False,
        )  # fmt: skip
        res = dataclasses.replace(more, iterations=res.iterations + more.iterations)
    if res.converged:
        return res
    res0 = res_start if res_start is not None else _relative_residual(matvec, rhs, start)
    return _never_worse(res, start, res0)


def _never_worse(res: PCGResult, start: torch.Tensor, res0: torch.Tensor) -> PCGResult:
    """``res`` with the start kept for the images it ended farther from the solution.

    A solve that broke down (the float32 operator not positive definite on a near-flat
    matting base, seen in late alternations of converged runs) can end worse than it began.
    """
    worse = ~(res.residual <= res0)  # NaN counts as worse
    if not bool(worse.any()):
        return res
    logger.info(
        "shading solve ended with relative residual %s above its start's %s; keeping the start",
        res.residual.tolist(),
        res0.tolist(),
    )
    x = torch.where(worse.view(-1, 1, 1, 1), start, res.x)
    return dataclasses.replace(res, x=x, residual=torch.where(worse, res0, res.residual))


def _relative_residual(
    matvec: Callable[[torch.Tensor], torch.Tensor], rhs: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """``||rhs - A x|| / ||rhs||`` per image, ``(B,)``; NaN (an overflowed ``x``) as ``inf``."""
    r = (rhs - matvec(x)).flatten(1).norm(dim=1) / rhs.flatten(1).norm(dim=1).clamp_min(1e-30)
    return torch.nan_to_num(r, nan=math.inf)


def _solve_in_float64(task: _Task, x0: torch.Tensor) -> PCGResult | None:
    """The same shading solve with every tensor in float64, from ``x0``.

    Returns the result in ``x0``'s dtype (its residual as float64 measures it: the float32
    product is what cannot resolve it), or ``None`` where float64 is not available (MPS).
    """
    problem = task.problem
    if problem.image.device.type == "mps":
        return None
    changes = {
        f.name: v.to(torch.float64)
        for f in dataclasses.fields(problem)
        if torch.is_tensor(v := getattr(problem, f.name)) and v.is_floating_point()
    }
    in_float64 = dataclasses.replace(
        task, problem=dataclasses.replace(problem, **changes), o=task.o.replace(warm_cg_max_iter=0)
    )
    sub = _solve(in_float64, x0=x0.to(torch.float64), cache=None, warn=False)
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


def _result(
    res: PCGResult,
    anchored: AnchoredSystem,
    image: torch.Tensor,
    o: ShadingParameters,
    times: dict[str, float],
    warn: bool,
) -> ShadingResult:
    """The layers of the solution ``res.x``, finite and on the gauge of the image."""
    m, area, target = anchored.inside, anchored.area, anchored.target
    b = image.shape[0]
    # a row the priors barely constrain (every pair cut) can make an early-stopped,
    # Jacobi-preconditioned solve overflow in float32; keep s finite and within 1e±8 of the
    # light's level (beyond any real shading) so the next alternation and R = I / S stay defined
    bound = -2.0 * math.log(o.dark_eps)
    s = torch.nan_to_num(res.x, nan=0.0, posinf=bound, neginf=-bound).clamp_(-bound, bound) * m
    s = s + (target - (s * m).flatten(1).sum(1).view(b, 1, 1, 1) / area) * m
    if warn and not res.converged:
        warnings.warn(
            f"shading PCG stopped after {res.iterations} iterations with relative residual "
            f"{float(res.residual.max()):.3g} > tol {o.cg_tol:g}; raise cg_max_iter or "
            "warm-start",
            ConvergenceWarning,
            stacklevel=4,  # the caller of solve_shading
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
