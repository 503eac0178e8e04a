"""Stage 1's linear system: the shading priors of Eq. 1 and the anchor of their constant.

:func:`build_shading_system` is the one place the priors are built; :class:`ShadingSystemCache`
keeps what does not change between the alternations on one image; :func:`anchored_system`
makes the energy positive definite, the system :func:`~torchiid.stages.shading.solve_shading`
hands to PCG.

Normalisation. Every term annihilates constants (``S_l`` fixes ``s`` only up to a shift of
each connected group of pixels), so a tiny anchor ``alpha * sum_i (s_i - t)^2`` over the region
makes the system positive definite, with ``alpha = anchor * mean(diag(Psi))`` and ``t`` the
mean of ``log p`` over the region (``p`` = channel-mean intensity, clamped to ``dark_eps``).
Because ``Psi 1 = 0``, the exact minimiser then has mean ``s`` equal to ``t``: the geometric
mean of the shading equals that of the intensity (reflectance's geometric mean is about 1).
After the solve ``s`` is shifted to satisfy this exactly (removing float round-off drift).

Speed. The products never touch a sparse matrix: ``S_l``, ``S_m`` and ``S_s`` are 3x3 stencils,
``S_p`` is converted once to an equivalent signed 5x5 stencil
(:meth:`MattingQuadratic.as_stencil`), and they merge into one 12-offset shifted product;
``S_c`` is a small sparse product.
Without a warm start, ``coarse_levels > 1`` first solves 2x-downsampled copies of the problem
and upsamples their solution as the initial guess (cascadic CG): the Jacobi-PCG iteration count on
these near-binary, strongly varying weights is dominated by smooth, low-frequency error that the
coarse levels remove cheaply. The assembled torch sparse matrices (``to_sparse()`` of every
term) are the tested reference.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from torchiid.core.cache import InputKey, input_key
from torchiid.core.check import check_image, check_shape
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.params import ShadingParameters
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
from torchiid.priors.texture import detexture
from torchiid.stages.config import ShadingProblem, check_group

__all__ = [
    "ShadingSystem",
    "ShadingSystemCache",
    "build_shading_system",
    "assemble_shading_system",
    "matting_base",
    "smoothed_base",
    "coarse_problem",
    "AnchoredSystem",
    "anchored_system",
]

#: a term builder and the key of its inputs (``None``: never cached)
_Maker = tuple[Callable[[], QuadraticTerm], "InputKey | tuple | None"]


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
            long as it keeps its iteration count (see ``shading_preconditioner``).
        fresh_iterations: the PCG iterations it needed on the system it was built for.
        neighbourhood: ``S_c``'s neighbours and LLE weights, shared with the coarser levels
            of a coarse-to-fine solve (which build ``S_c`` on their own grids from the same
            features).
        texture: ``S_l``'s texture confidence made by the solve for a problem without one,
            with the key of its inputs.
    """

    terms: dict[str, tuple[InputKey, QuadraticTerm]] = field(default_factory=dict)
    texture: tuple[InputKey, torch.Tensor] | None = None
    hits: int = 0
    preconditioner: object | None = None
    fresh_iterations: int = 0
    neighbourhood: LLENeighbourhood = field(default_factory=LLENeighbourhood)

    def reuse(self, name: str, key: object, build: Callable[[], QuadraticTerm]) -> QuadraticTerm:
        """The term kept under ``name`` if made from the inputs ``key``, else ``build()``.

        ``key`` ``None``: the term is always built and not kept.
        """
        kept = self.terms.get(name) if key is not None else None
        if kept is not None and kept[0] == key:
            self.hits += 1
            return kept[1]
        term = build()
        if key is not None:
            self.terms[name] = (key, term)
        return term


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
    copy of the shading's edges in the base (``R^β I^(1−β) ≈ R S^(1−β)``), so the term does
    not work against them as it does with ``mix = 1``. ``mix = 0``: the smoothed image in
    every alternation.

    Shape:
        image, reflectance ``(B, 3, H, W)`` (linear), mask ``(B, 1, H, W)`` or ``None``.
    """
    if mix >= 1:
        return reflectance
    smooth = smoothed_base(image, mask, sigma)
    if mix <= 0:
        return smooth
    # fractional powers need positive bases: black (or, from a caller, negative) values are
    # raised to a floor far below any visible level
    floor = max(1e-8, torch.finfo(image.dtype).tiny)
    return reflectance.clamp_min(floor).pow(mix) * smooth.clamp_min(floor).pow(1.0 - mix)


def smoothed_base(image: torch.Tensor, mask: torch.Tensor | None, sigma: float) -> torch.Tensor:
    """Gaussian-smoothed image; inside a mask a normalised convolution (outside ignored)."""
    if mask is None:
        return smooth_base(image, sigma)
    m = mask.to(image.dtype)
    num = smooth_base(image * m, sigma)
    den = smooth_base(m, sigma)
    return torch.where(den > 0, num / den.clamp_min(1e-12), image) * m


def coarse_problem(problem: ShadingProblem, base_sigma: float, base_mix: float) -> ShadingProblem:
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
        base = smoothed_base(image, mask, base_sigma)
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
        texture=None if problem.texture is None else down(problem.texture),
    )


def sync(device: torch.device) -> None:
    """Wait for the device's queued work (timings of asynchronous CUDA work)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _checked_mask(mask: torch.Tensor | None, image: torch.Tensor) -> None:
    if mask is None:
        return
    b, _, h, w = image.shape
    check_shape(mask, (b, 1, h, w), "mask")
    if mask.dtype != torch.bool:
        raise ShapeError(f"mask must be a bool tensor, got {mask.dtype}")
    if not bool(mask.flatten(1).any(1).all()):
        raise ParameterError("mask is empty for at least one image: nothing to solve")


def _global_makers(
    problem: ShadingProblem,
    image: torch.Tensor,
    o: ShadingParameters,
    weights: Mapping[str, float],
    cache: ShadingSystemCache | None,
    seed: int,
) -> dict[str, _Maker]:
    """Builders of ``S_c`` (LLE constraints) and ``S_p`` (matting propagation), when on."""
    mask, b, (h, w) = problem.mask, image.shape[0], image.shape[-2:]
    dev, dt = image.device, image.dtype
    makers: dict[str, _Maker] = {}
    centers, feats = problem.patch_centers, problem.patch_features
    # one patch (an image of one patch size) has no neighbour to tie it to: no S_c rows
    single = feats is not None and feats.dim() == 3 and feats.shape[1] < 2
    if weights["S_c"] > 0 and (centers is not None or feats is not None) and not single:
        if centers is None or feats is None:
            raise ParameterError("S_c needs both patch_centers and patch_features")
        lle = (o.lle_k, o.lle_reg, o.lle_neighbours)
        makers["S_c"] = (
            lambda: lle_term(
                centers.to(dev), feats.to(device=dev, dtype=dt), h, w, k=o.lle_k,
                reg=o.lle_reg, neighbours=o.lle_neighbours, mask=mask, seed=seed,
                reuse=None if cache is None else cache.neighbourhood,
            ),
            input_key(centers, feats, h, w, *lle, mask, seed, dt, dev),
        )  # fmt: skip
    if weights["S_p"] > 0:
        base = problem.base_image
        if base is not None:
            base = base.contiguous()
            check_image(base, "base_image", channels=3, nonnegative=False)
            check_shape(base, (b, 3, h, w), "base_image")
        makers["S_p"] = (
            lambda: matting_stencil(
                smoothed_base(image, mask, o.base_sigma)
                if base is None
                else matting_base(image, base.to(dt), mask, o.base_sigma, o.base_mix),
                eps=o.matting_eps,
                mask=mask,
            ),
            None,
        )
    return makers


def _local_makers(
    problem: ShadingProblem,
    image: torch.Tensor,
    given: torch.Tensor,
    o: ShadingParameters,
    weights: Mapping[str, float],
) -> dict[str, _Maker]:
    """Builders of ``S_m`` (proposal affinity), ``S_l`` (Retinex) and ``S_s``, when on."""
    mask, b, (h, w) = problem.mask, image.shape[0], image.shape[-2:]
    dev, dt = image.device, image.dtype
    stencil = shading_stencil(h, w, device=dev)
    makers: dict[str, _Maker] = {}
    sim = problem.similarity
    if sim is not None and weights["S_m"] > 0:
        makers["S_m"] = (
            lambda: midlevel_term(sim.to(dt), stencil, o.t_m, mask),
            input_key(sim, o.t_m, mask, dt),
        )
    if weights["S_l"] > 0:
        confident = o.dark_level > 0 or o.clip_level > 0
        marks = (o.t_c, o.t_b, o.t_i, o.t_e, o.t_d, o.t_h, o.t_x, o.t_x_sigma, o.t_xc)
        texture = problem.texture
        makers["S_l"] = (
            lambda: retinex_term(
                detexture(image, o.t_x, mask, o.dark_eps, o.t_x_sigma, o.t_xc, texture)
                if o.t_x > 0
                else image,
                stencil, o.t_c, o.t_b, o.dark_eps, mask,
                confidence=(
                    pixel_confidence(image, o.dark_level, o.clip_level) if confident else None
                ),
                t_i=o.t_i, t_e=o.t_e, t_d=o.t_d, t_h=o.t_h,
            ),
            # the caller's tensor: the cache key refers to it, not to a contiguous copy
            input_key(given, *marks, o.dark_eps, o.dark_level, o.clip_level, mask, texture),
        )  # fmt: skip
    if weights["S_s"] > 0:
        makers["S_s"] = (
            lambda: smoothness_term(stencil, b, mask, dt),
            input_key(b, h, w, mask, dt, dev),
        )
    return makers


def assemble_shading_system(
    problem: ShadingProblem,
    shading: ShadingParameters,
    weights: Mapping[str, float],
    cache: ShadingSystemCache | None = None,
    seed: int = 0,
) -> ShadingSystem:
    """:func:`build_shading_system` with each prior's weight given (``shading.weights()``)."""
    given = problem.image
    check_image(given, "image", channels=3, min_side=3)
    # channels-last strides (a permuted HxWx3 array) slow every shifted product down
    image = given.contiguous()
    _checked_mask(problem.mask, image)
    makers = _global_makers(problem, image, shading, weights, cache, seed)
    makers.update(_local_makers(problem, image, given, shading, weights))
    terms: dict[str, tuple[float, QuadraticTerm]] = {}
    times: dict[str, float] = {}
    for name, (build, key) in makers.items():
        t0 = time.perf_counter()
        term = build() if cache is None else cache.reuse(name, key, build)
        sync(image.device)
        times[name] = time.perf_counter() - t0
        terms[name] = (weights[name], term)
    if not terms:
        raise ParameterError("every shading term is switched off; enable at least one")
    return ShadingSystem(SumQuadratic(list(terms.values())), terms, times)


def build_shading_system(
    problem: ShadingProblem,
    shading: ShadingParameters,
    cache: ShadingSystemCache | None = None,
    *,
    seed: int = 0,
) -> ShadingSystem:
    """Assemble ``Psi`` (Eq. 1) without the anchor: the one place the shading priors are built.

    Args:
        problem: the tensors (:class:`~torchiid.stages.config.ShadingProblem`).
        shading: the stage's parameters (:class:`~torchiid.params.ShadingParameters`, e.g.
            ``params.alternation(k)[0]``): each prior's weight is ``shading.weights()``, 0 is
            off (``S_c`` also needs patch centres and features, ``S_m`` the similarities;
            ``S_p`` without a base image uses the Gaussian-smoothed image).
        cache: a :class:`ShadingSystemCache` kept across the alternations on one image.
        seed: seed of random LLE neighbours (``Parameters.seed``).

    Returns:
        :class:`ShadingSystem`.
    """
    group = check_group("build_shading_system", shading, ShadingParameters, "shading")
    return assemble_shading_system(problem, group, group.weights(), cache, seed)


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
    constant; pixels outside ``mask`` are pinned to ``s = 0``.

    Args:
        total: ``build_shading_system(...).total``.
        image: ``(B, 3, H, W)`` linear RGB.
        mask: ``(B, 1, H, W)`` bool or ``None``.
        anchor: ``ShadingParameters.anchor``.
        dark_eps: ``ShadingParameters.dark_eps``.

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
