"""Stage 2's sparsity priors (Eq. 12): ``A``, ``B`` and ``C`` built, and what they keep.

:func:`build_reflectance_terms` is the one place the priors are made (see
:mod:`torchiid.stages.reflectance` for the method's notes); :class:`ReflectanceCache` keeps
what does not change between the alternations on one image.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch

from torchiid.core.cache import InputKey, input_key
from torchiid.core.check import check_finite, check_image, check_same_batch, check_shape
from torchiid.core.exceptions import ShapeError
from torchiid.params import ReflectanceParameters
from torchiid.priors import kernels
from torchiid.priors.reflectance_terms import (
    COLOUR_WEIGHTS,
    REPLAY_STEPS,
    StencilL1Term,
    lab_features,
    merged_stencil_affinity,
    stencil_affinity,
)
from torchiid.priors.representatives import (
    SegmentLayout,
    global_pair_term,
    representative_pixels,
    segment_layout,
)
from torchiid.priors.stencil import Stencil
from torchiid.stages.config import ReflectanceProblem, check_group
from torchiid.stages.temporal import temporal_term

__all__ = [
    "ReflectanceCache",
    "ReflectanceTerms",
    "build_reflectance_terms",
    "assemble_reflectance_terms",
]

logger = logging.getLogger(__name__)


@dataclass
class ReflectanceCache:
    """Parts of Eq. 12 that do not change between the alternations on one image.

    The proposal-feature factor ``exp(−‖Δg̊‖²/2t_g²)`` of ``B``'s weights (Eq. 9) depends only
    on Stage 0's ``g̊`` and the mask, not on the current ``ρ``, so the pipeline computes it once
    per image batch and reuses it; it is recomputed when its inputs (same tensors, unmodified)
    or parameters differ. It also keeps the storage of the Bregman variable (``(B, 3, K, H, W)``,
    the stage's largest tensor, in 16-bit fixed point: see
    :class:`~torchiid.priors.reflectance_terms.StencilL1Term`) and of the merged ``A``/``B``
    weights, so that later alternations write into memory already in use.

    Attributes:
        semantic: (key of the inputs, ``(B, K, H, W)`` factor) or ``None``.
        layout: (key of the segments and mask, their
            :class:`~torchiid.priors.representatives.SegmentLayout`) for ``C``'s
            representatives, or ``None``.
        hits: how many computations were skipped.
        state_valid: the storage holds the last solve's Bregman variable of the local term
            (what ``bregman_warm_state`` starts the next solve from).
        state_step: the step of that variable's fixed-point values.
        theta: the Split-Bregman penalty that variable was written at (it changes with
            ``bregman_theta_floor``; the next warm solve starts there).
        last: no later solve on this image will use the cache (the last alternation sets
            it): ``B``'s factor is then not kept (one kept is let go), the merged weights are
            written over it and the weights' storage of earlier alternations is let go, so
            the solve holds one ``(B, K, H, W)`` tensor of weights, not two.
    """

    semantic: tuple[InputKey, torch.Tensor] | None = None
    layout: tuple[InputKey, SegmentLayout] | None = None
    hits: int = 0
    state_valid: bool = False
    state_step: float | None = None
    theta: float | None = None
    last: bool = False
    _state: torch.Tensor | None = None
    _weights: torch.Tensor | None = None

    def reuse(self, slot: str, key: InputKey, compute: Callable[[], Any]) -> Any:
        """The value kept in ``slot`` if it was made from the inputs ``key``, else ``compute()``.

        ``slot`` is ``"semantic"`` or ``"layout"``; a computed value is kept there (with
        ``key``) for the next call, and every reuse counts in :attr:`hits`.
        """
        kept = getattr(self, slot)
        if kept is not None and kept[0] == key:
            self.hits += 1
            return kept[1]
        value = compute()
        setattr(self, slot, (key, value))
        return value

    def state_buffer(
        self, like: torch.Tensor, num_offsets: int, fixed_point: bool = True
    ) -> torch.Tensor:
        """Storage ``(B, C, K, H, W)`` for the Bregman variable, reused across calls.

        ``torch.int16`` (16-bit fixed point) by default; ``like``'s dtype with
        ``fixed_point=False`` (thresholds too small for it, see
        :func:`~torchiid.priors.kernels.fixed_point_fits`).
        """
        b, c, h, w = like.shape
        shape = (b, c, num_offsets, h, w)
        dtype = torch.int16 if fixed_point else like.dtype
        st = self._state
        if st is None or st.shape != shape or st.dtype != dtype or st.device != like.device:
            self._state = st = like.new_empty(shape, dtype=dtype)
            self.state_valid = False
        return st

    def release_weights(self) -> None:
        """Let go of the merged weights' storage (a solve that will not reuse it)."""
        self._weights = None

    def weights_buffer(self, like: torch.Tensor, num_offsets: int) -> torch.Tensor:
        """Storage ``(B, K, H, W)`` for the merged ``A``/``B`` weights, reused across calls.

        Each alternation's weights replace the last one's (whose solve is over), so the
        pages of this 47 MB tensor (at 512×384) are faulted in once per image, not once per
        alternation.
        """
        b, _, h, w = like.shape
        shape = (b, num_offsets, h, w)
        buf = self._weights
        if (
            buf is None
            or buf.shape != shape
            or buf.dtype != like.dtype
            or buf.device != like.device
        ):
            self._weights = buf = like.new_empty(shape)
        return buf


@dataclass(frozen=True)
class ReflectanceTerms:
    """Eq. 12's sparsity priors as built by :func:`build_reflectance_terms`.

    Attributes:
        terms: name -> ``(gamma, term)`` of every active L1 term, in solver order: ``"A+B"``
            (the merged local and mid-level term) or ``"A"`` and ``"B"``, then ``"C"``, then
            the temporal term ``"T"`` when the problem has a ``temporal`` prior.
        num_representatives: ``(B,)`` size of ``Q`` (0 when ``C`` is off).
        timings: seconds for the colour features, ``A``'s, ``B``'s and ``C``'s weights.
    """

    terms: dict[str, tuple[float, object]]
    num_representatives: torch.Tensor
    timings: tuple[float, float, float, float]


def _check_problem(problem: ReflectanceProblem) -> None:
    rho, image, mask = problem.rho, problem.image, problem.mask
    check_image(rho, "rho")
    check_image(image, "image")
    check_same_batch(rho, image, names=["rho", "image"])
    b, _, h, w = rho.shape
    if mask is not None:
        check_shape(mask, (b, 1, h, w), "mask")
        if mask.dtype != torch.bool:
            raise ShapeError(f"expected a bool mask, got {mask.dtype}")
    if problem.gpca is not None:
        check_shape(problem.gpca, (b, "d", h, w), "gpca")
        check_finite(problem.gpca, "gpca")
    if problem.segments is not None:
        check_shape(problem.segments, (b, h, w), "segments")
    if problem.temporal is not None:
        check_shape(problem.temporal.target, (b, 3, h, w), "temporal target")
        check_finite(problem.temporal.target, "temporal target")
        check_shape(problem.temporal.confidence, (b, 1, h, w), "temporal confidence")
        check_finite(problem.temporal.confidence, "temporal confidence")


def _semantic_factor(
    gpca: torch.Tensor,
    like: torch.Tensor,
    o: ReflectanceParameters,
    stencil: Stencil,
    mask: torch.Tensor | None,
    cache: ReflectanceCache | None,
) -> torch.Tensor:
    """``B``'s proposal-feature factor ``exp(−‖Δg̊‖²/2t_g²)`` (Eq. 9), from the cache if kept."""
    t_m = o.t_g or o.t

    def factor() -> torch.Tensor:
        return stencil_affinity(gpca.to(like.dtype), stencil, t_m, mask)

    if cache is None:
        return factor()
    key = input_key(gpca, t_m, mask, like.dtype, o.window)
    if cache.last:  # not kept: freed as soon as the caller lets it go
        kept, cache.semantic = cache.semantic, None
        if kept is not None and kept[0] == key:
            cache.hits += 1
            return kept[1]
        return factor()
    return cache.reuse("semantic", key, factor)


def _timed(make: Callable[[], torch.Tensor]) -> tuple[torch.Tensor, float]:
    """``make()`` and the seconds it took."""
    t0 = time.perf_counter()
    value = make()
    return value, time.perf_counter() - t0


def _stencil_terms(
    rho: torch.Tensor,
    rbar: torch.Tensor,
    semantic: Callable[[], torch.Tensor] | None,
    stencil: Stencil,
    o: ReflectanceParameters,
    weights: Mapping[str, float],
    mask: torch.Tensor | None,
    cache: ReflectanceCache | None,
    merge: bool,
) -> tuple[dict[str, tuple[float, object]], float]:
    """``A`` and ``B`` (Eqs. 8-9): one merged term ``"A+B"`` when both are on and ``merge``.

    ``semantic`` makes ``B``'s factor (``None``: ``B`` is off). Where nothing keeps the
    factor (no cache, or the last alternation) the merged weights are written over it, so the
    solve holds one ``(B, K, H, W)`` tensor of weights; otherwise they go to the cache's
    storage. Returns the terms and the seconds spent making the factor.
    """
    use_a = weights["A"] > 0
    seconds = 0.0
    if use_a and semantic is not None and merge:
        gl, gm = weights["A"], weights["B"]
        e_g, seconds = _timed(semantic)
        if cache is None or cache.last:
            # nothing else holds the factor (see ReflectanceCache.last): the weights replace it
            if cache is not None:
                cache.release_weights()
            out = e_g
        else:
            out = cache.weights_buffer(rho, stencil.num_offsets)
        merged = merged_stencil_affinity(rbar, e_g, stencil, o.t, gl, gm, mask, out=out)
        del e_g, out
        # 16-bit fixed point unless λ = γ / θ is too small for it (then float32)
        fixed = kernels.fixed_point_fits(float(gl + gm) / (o.theta * o.value_scale))
        state = None
        if cache is not None:
            state = cache.state_buffer(rho, stencil.num_offsets, fixed_point=fixed)
        warm = o.bregman_warm_state and cache is not None and cache.state_valid
        term = StencilL1Term(
            stencil,
            merged,
            zero_invalid=False,
            state=state,
            warm=warm,
            state_step=cache.state_step if warm else None,
            # only a later warm start reads the last update's state
            keep_state=o.bregman_warm_state and cache is not None,
            replay=o.bregman_iter <= REPLAY_STEPS + 1,  # every update's history short enough
        )
        if cache is not None:
            cache.state_valid = False  # valid again once the solve has written it
        return {"A+B": (float(gl + gm), term)}, seconds
    terms: dict[str, tuple[float, object]] = {}
    if use_a or semantic is not None:
        v_l = stencil_affinity(rbar, stencil, o.t, mask)
        if use_a:
            terms["A"] = (float(weights["A"]), StencilL1Term(stencil, v_l, zero_invalid=False))
        if semantic is not None:
            e_g, seconds = _timed(semantic)
            terms["B"] = (
                float(weights["B"]),
                StencilL1Term(stencil, e_g * v_l, zero_invalid=False),
            )
    return terms, seconds


def _global_term(
    problem: ReflectanceProblem,
    rbar: torch.Tensor,
    o: ReflectanceParameters,
    gamma: float,
    cache: ReflectanceCache | None,
) -> tuple[tuple[float, object] | None, torch.Tensor]:
    """``C`` (Eq. 10) over the segments' representative pixels, and their number per image."""
    mask = problem.mask
    layout = None
    if cache is not None:
        key = input_key(problem.segments, mask)
        layout = cache.reuse("layout", key, lambda: segment_layout(problem.segments, mask))
    reps = representative_pixels(rbar, problem.segments, mask, layout=layout)
    return (float(gamma), global_pair_term(rbar, reps, o.t)), reps.counts


def assemble_reflectance_terms(
    problem: ReflectanceProblem,
    reflectance: ReflectanceParameters,
    weights: Mapping[str, float],
    cache: ReflectanceCache | None = None,
    merge: bool = True,
) -> ReflectanceTerms:
    """:func:`build_reflectance_terms` with each sparsity prior's weight given."""
    _check_problem(problem)
    o = reflectance
    rho, mask, gpca = problem.rho.contiguous(), problem.mask, problem.gpca
    b, _, h, w = rho.shape
    if weights["B"] > 0 and gpca is None:
        logger.debug("gamma_m > 0 but no gpca given: mid-level term B is off")
    stencil = Stencil.square(h, w, o.window, device=rho.device)
    t0 = time.perf_counter()
    w_l, lab_scale = COLOUR_WEIGHTS[o.colour_weights]
    lum = w_l if o.luminance_weight is None else o.luminance_weight
    rbar = lab_features(rho, luminance_weight=lum, lab_scale=lab_scale)
    t1 = time.perf_counter()
    semantic = None
    if weights["B"] > 0 and gpca is not None:
        semantic = functools.partial(_semantic_factor, gpca, rho, o, stencil, mask, cache)
    terms, t_semantic = _stencil_terms(rho, rbar, semantic, stencil, o, weights, mask, cache, merge)
    t3 = time.perf_counter()
    nrep = torch.zeros(b, dtype=torch.long, device=rho.device)
    if weights["C"] > 0 and problem.segments is not None:
        terms["C"], nrep = _global_term(problem, rbar, o, weights["C"], cache)
    if problem.temporal is not None:
        term = temporal_term(problem.temporal, rho, o, mask=mask)
        if term is not None:
            terms["T"] = term
    t4 = time.perf_counter()
    return ReflectanceTerms(terms, nrep, (t1 - t0, t3 - t1 - t_semantic, t_semantic, t4 - t3))


def build_reflectance_terms(
    problem: ReflectanceProblem,
    reflectance: ReflectanceParameters,
    cache: ReflectanceCache | None = None,
    *,
    merge: bool = True,
) -> ReflectanceTerms:
    """Build the sparsity priors of Eq. 12: the one place ``A``, ``B`` and ``C`` are made.

    Args:
        problem: the tensors (:class:`~torchiid.stages.config.ReflectanceProblem`); ``B`` needs
            ``gpca`` and ``C`` needs ``segments``.
        reflectance: the stage's parameters (:class:`~torchiid.params.ReflectanceParameters`,
            e.g. ``params.alternation(k)[1]``); each prior's weight is
            ``reflectance.weights()``, 0 is off.
        cache: reuse ``B``'s proposal-feature factor and the Bregman-state storage.
        merge: build ``A`` and ``B`` as one exactly equivalent term ``"A+B"`` (see
            :mod:`torchiid.stages.reflectance`).

    Returns:
        :class:`ReflectanceTerms`.
    """
    o = check_group("build_reflectance_terms", reflectance, ReflectanceParameters, "reflectance")
    return assemble_reflectance_terms(problem, o, o.weights(), cache, merge)
