"""The whole method (Saini & Narayanan, §3 and §3.4).

Stage 0 features, then k alternations of Stage 1 (L2 shading) and Stage 2 (L1 reflectance),
then the layers at the input's resolution: :func:`decompose` reads as the paper's algorithm,
each step a function of the module that owns it (:mod:`torchiid.pipeline`).

:func:`decompose` is the functional core and :class:`IntrinsicDecomposer` its ``nn.Module``
twin. Both take **linear** RGB ``(B, 3, H, W)`` tensors on any device and return a
:class:`Decomposition` whose layers satisfy ``image == reflectance * shading`` exactly (up to
floating-point rounding) inside the mask.

Scale: the reflectance is returned as an albedo in ``[0, 1]`` and the gray shading carries the
rest (see :func:`full_resolution_layers`).

Resolution: the method runs at a working resolution (``params.output.max_side``, default 512
px on the longer side); the shading is brought back to the input's resolution edge-aware and
``R = I / S`` there, band by band, so a 12-megapixel photo costs a few full-resolution layers.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import torch
from torch import nn

from torchiid._version import __version__
from torchiid.core.compiling import eager_under_compile
from torchiid.core.exceptions import ParameterError
from torchiid.core.memory import release_free_memory
from torchiid.features.semantic import SemanticFeatures, semantic_features
from torchiid.params import PRESETS, Parameters
from torchiid.pipeline.alternation import Alternation, texture_map, warn_unconverged
from torchiid.pipeline.coarse import coarse_alternations, coarse_size, hand_over
from torchiid.pipeline.inputs import WorkingInputs, working_inputs
from torchiid.pipeline.layers import (
    FullLayers,
    OutputLayers,
    full_resolution_layers,
    output_layers,
)
from torchiid.pipeline.memory import (
    BYTES_PER_FULL_PIXEL,
    BYTES_PER_WORKING_PIXEL,
    MEMORY_CHECK_VARIABLE,
    MEMORY_OVERHEAD,
    check_memory,
    memory_needed,
)
from torchiid.pipeline.results import Decomposition, IterationLayers, SolveReport
from torchiid.stages.config import TemporalPrior

__all__ = [
    "Decomposition",
    "SolveReport",
    "FullLayers",
    "IterationLayers",
    "decompose",
    "full_resolution_layers",
    "IntrinsicDecomposer",
    "memory_needed",
    "check_memory",
    "BYTES_PER_WORKING_PIXEL",
    "BYTES_PER_FULL_PIXEL",
    "MEMORY_OVERHEAD",
    "MEMORY_CHECK_VARIABLE",
]


@torch.no_grad()
def decompose(
    image: torch.Tensor,
    params: Parameters | None = None,
    *,
    mask: torch.Tensor | None = None,
    features: SemanticFeatures | None = None,
    return_iterations: bool = False,
    return_stage1: bool = True,
    progress: Callable[[str, int, int], None] | None = None,
    init: tuple[torch.Tensor, torch.Tensor] | None = None,
    temporal: TemporalPrior | None = None,
    return_features: bool = False,
    schedule_start: int = 1,
) -> Decomposition:
    """Decompose linear RGB images into reflectance and shading (the paper's full method).

    Args:
        image: ``(B, 3, H, W)`` or ``(3, H, W)`` **linear** RGB, values ``>= 0`` (typically in
            ``[0, 1]``), sides of at least ``params.features.patch_size`` pixels. Images of a
            batch are solved together as one block-diagonal system.
        params: :class:`~torchiid.params.Parameters` (default: the ``default`` preset). With
            ``params.coarse_scale`` below 1 (the ``default``: 0.5) the alternations before the
            last run on the image at that scale and their shading starts the last one
            (:mod:`torchiid.pipeline.coarse`), unless ``init``, ``temporal`` or
            ``schedule_start`` give the start.
        mask: optional ``(B, 1, H, W)`` (or ``(H, W)``, ``(B, H, W)``) tensor, bool or numbers:
            nonzero is inside, as everywhere in torchiid (:func:`~torchiid.core.check.as_mask`);
            every prior is restricted to the pixels inside and the outside is returned as 0.
        features: precomputed Stage 0 features (at the working resolution), e.g. to run
            several parameter sets on one image.
        return_iterations: keep every alternation's ``σ, ρ, R, S`` (paper Fig. 5; those of
            coarse alternations brought up to the working resolution).
        return_stage1: also bring the last Stage 1 layers ``σ, ρ`` to full resolution
            (``False`` saves two full-resolution layers on large photos).
        progress: called as ``progress(stage, k, total)`` with stage ``"features"`` (``k = 0``)
            and then ``"iteration"`` after each alternation run, ``k = 1..total``, where
            ``total`` is the number of alternations run (``params.iterations -
            schedule_start + 1``), so a bar over ``total`` ends full.
        init: a warm start ``(R0, S0)`` (e.g. a network's prediction) at the input's
            resolution or at the working resolution: reflectance ``(B, 3, H, W)`` and
            shading ``(B, 1, H, W)`` (or ``(B, 3, H, W)``, averaged to gray), positive. The
            first alternation's shading PCG starts from ``log S0`` (instead of the
            coarse-to-fine cascade; its iterations are then capped by
            ``warm_cg_max_iter`` like later alternations) and its Split-Bregman from
            ``z = c·R0`` (instead of ``ρ``), ``c`` the least-squares fit of ``R0`` to Stage
            1's ``ρ`` (the scale of ``R0 · S0`` does not matter). Only the starting points
            change, not the energies (the matting base of the first ``S_p`` stays the
            smoothed image): when the solves converge the result is the cold start's.
        temporal: a :class:`~torchiid.stages.config.TemporalPrior` at the input's
            resolution or at the working resolution (video: the previous frame's reflectance
            warped onto this frame, and where that warp is trusted): every alternation's
            Stage 2 adds a term pulling the reflectance toward it (an L2 anchor or an L1
            term, relative to the data term; the target's scale does not matter). Brought to
            the working resolution by area averaging (the target weighted by the
            confidence); the confidence is 0 outside the mask. ``None`` (default): Eq. 12 as
            in the paper. :mod:`torchiid.video` builds it from optical flow.
        return_features: keep the Stage 0 features in ``Decomposition.features`` (to pass
            them as ``features=`` for another image of the same scene).
        schedule_start: run only the alternations ``schedule_start..params.iterations`` of
            the §3.4 schedule, with their weights (default 1: all of them). With a warm start
            that is already near the answer (the next frame of a video) the last alternations
            refine it; the first alternation still starts from ``init`` (or cold).

    Returns:
        :class:`Decomposition` at the input's resolution and dtype. float16 and bfloat16
        inputs are solved in float32 (their range and precision cannot hold the solver's
        systems) and the layers returned in the input dtype. Outputs are detached (the
        method is an optimisation, not a differentiable layer).

    Example:
        >>> from torchiid.synthetic import mondrian
        >>> img = mondrian(64, 64).image
        >>> p = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)
        >>> out = decompose(img, p)
        >>> out.reflectance.shape, out.shading.shape
        (torch.Size([1, 3, 64, 64]), torch.Size([1, 1, 64, 64]))
        >>> bool(torch.allclose(out.reflectance * out.shading, img, atol=1e-5))
        True
        >>> bool(out.reflectance.max() <= 1)
        True
    """
    params = _checked_params(params)
    if progress is not None and not callable(progress):
        raise ParameterError(
            f"progress must be a callable progress(stage, k, total), got {type(progress).__name__}"
        )
    t_start = time.perf_counter()
    work = working_inputs(
        image, mask, params, init=init, temporal=temporal, schedule_start=schedule_start,
        return_stage1=return_stage1, return_iterations=return_iterations,
    )  # fmt: skip
    # Stage 0: the semantic features (§3.1), unless given
    stage0 = features is None
    if stage0:
        features = semantic_features(work.image, params)
    times = dict(features.times)
    # S_l's texture marks, at the working resolution for every alternation: after Stage 0,
    # whose CNN pass sets a peak, in the memory its freed buffers leave
    t0 = time.perf_counter()
    texture = texture_map(work, params)
    if texture is not None:
        times["texture marks"] = time.perf_counter() - t0
    if stage0:
        release_free_memory()  # Stage 0's buffers and the marks', before the solves' peak
    total = params.iterations - work.first + 1  # the alternations this call runs
    if progress is not None:
        progress("features", 0, total)

    def done(k: int, alternations: Alternation) -> None:
        _check_finite_solves(alternations.solves, params, k)
        if progress is not None:
            progress("iteration", k - work.first + 1, total)

    # k alternations of Stage 1 (L2 shading) and Stage 2 (L1 reflectance); with coarse_scale
    # below 1, all but the last on the image at that scale, the last starting where they end
    first = work.first
    run = Alternation(work, features, params, keep_layers=return_iterations, texture=texture)
    size = coarse_size(work, params)
    if size is not None:
        # a temporary: the half-size run and its caches go before the full-size alternation
        hand_over(
            coarse_alternations(work, features, params, size, run.keep_layers, done, texture),
            run,
        )
        release_free_memory()  # the half-size run's buffers, before the full-size one
        first = params.iterations
    for k in range(first, params.iterations + 1):
        shading, reflectance = params.alternation(k)  # the §3.4 schedule's weights
        run.shading_step(k, shading)
        if k == params.iterations:
            # no shading solve follows: its terms go, and their memory back to the system,
            # before the last reflectance solve takes the run's largest tensors
            run.release_shading_terms()
            release_free_memory()
        run.reflectance_step(k, reflectance)
        done(k, run)
    times.update(run.times)
    if params.converge:
        # the caller of decompose, under torch's no_grad wrapper
        warn_unconverged(run.solves, stacklevel=3)
    # the layers at the input's resolution: S brought up edge-aware, R = I / S in [0, 1]
    layers = output_layers(
        work, run.reflectance, run.sigma, run.layers, params, return_stage1=return_stage1
    )
    times["total"] = time.perf_counter() - t_start
    kept = features if return_features else None
    return _decomposition(work, layers, params, times, run.solves, kept)


def _check_finite_solves(solves: list, params: Parameters, k: int) -> None:
    """Stop a decomposition whose solve left the numbers float32 holds, naming the likely cause.

    A residual that is not finite means the system's values overflowed: no later alternation
    can recover, and the layers would be meaningless.
    """
    bad = next((s for s in solves if s.alternation == k and not math.isfinite(s.residual)), None)
    if bad is None:
        return
    grown = params.tau ** (k - 1) if params.tau >= 1 else params.tau ** (1 - k)
    raise ParameterError(
        f"the {bad.stage} solve of alternation {k} diverged (its residual is not finite): the "
        f"weights overflow float32; after {k - 1} alternations the §3.4 schedule has scaled "
        f"them by up to tau^{k - 1} = {grown:.3g} (tau {params.tau:g}), so use fewer "
        "iterations, a tau closer to 1 or smaller weights"
    )


def _checked_params(params: Parameters | None) -> Parameters:
    """``params``, or the ``default`` preset; anything else is a one-line error."""
    params = params if params is not None else Parameters.preset("default")
    if not isinstance(params, Parameters):
        hint = (
            "Parameters.from_dict(your_dict) or Parameters().replace(name=value)"
            if isinstance(params, dict)
            else "Parameters(), Parameters.preset(name) or Parameters.from_json(path)"
        )
        raise ParameterError(
            f"params must be a torchiid.Parameters, got {type(params).__name__}; use {hint}"
        )
    return params


def _decomposition(
    work: WorkingInputs,
    layers: OutputLayers,
    params: Parameters,
    times: dict[str, float],
    solves: list[SolveReport],
    features: SemanticFeatures | None,
) -> Decomposition:
    """The :class:`Decomposition` of ``layers``, in the input's dtype."""

    def back(x: torch.Tensor | None) -> torch.Tensor | None:
        return x if x is None or x.dtype == work.dtype else x.to(work.dtype)

    final, stage1 = layers.final, layers.stage1
    names = ("sigma", "rho", "reflectance", "shading")
    return Decomposition(
        reflectance=back(final.reflectance),
        shading=back(final.shading),
        sigma=None if stage1 is None else back(stage1.shading),
        rho=None if stage1 is None else back(stage1.reflectance),
        iterations=tuple(
            IterationLayers(*(back(getattr(it, n)) for n in names)) for it in layers.iterations
        ),
        params=params,
        times=times,
        mask=work.full_mask,
        shading_white=final.shading_white,
        albedo_excess=final.albedo_excess,
        working_size=work.size,
        solves=tuple(solves),
        features=features,
    )


class IntrinsicDecomposer(nn.Module):
    """``nn.Module`` twin of :func:`decompose` for use inside larger models.

    It has no tensors of its own; its ``state_dict()`` holds its parameters (the
    ``_extra_state`` entry), so a larger model saved and loaded keeps the decomposer's settings,
    and its ``repr`` names the nearest preset and the values that differ from it.

    ``torch.compile`` of a model holding it compiles the model around it and runs the
    decomposition as it is (:func:`decompose` is excluded from compilation: its solver loops
    depend on the data, and its features and kernels are NumPy, numba and onnxruntime calls).

    Args:
        params: the parameters (default: the ``default`` preset).
        return_iterations: keep every alternation's layers.

    Shape:
        input ``(B, 3, H, W)`` linear RGB; output :class:`Decomposition` with reflectance
        ``(B, 3, H, W)`` and shading ``(B, 1, H, W)``.

    Example:
        >>> from torchiid.synthetic import mondrian
        >>> p = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)
        >>> out = IntrinsicDecomposer(p)(mondrian(64, 64).image)
        >>> out.shading.shape
        torch.Size([1, 1, 64, 64])
    """

    def __init__(self, params: Parameters | None = None, return_iterations: bool = False):
        super().__init__()
        self.params = _checked_params(params)  # a bad value is named here, not at the first call
        self.return_iterations = return_iterations

    def forward(self, image: torch.Tensor, mask: torch.Tensor | None = None) -> Decomposition:
        """Decompose ``image``; see :func:`decompose`."""
        # left out of a compiled graph: dynamo would split the decomposition into hundreds
        # of graphs (and inductor mis-compiles some) for no gain
        run = eager_under_compile(decompose)
        return run(image, self.params, mask=mask, return_iterations=self.return_iterations)

    def extra_repr(self) -> str:
        """The nearest preset and the values that differ from it."""
        mine = self.params.to_dict()
        nearest, changes = "default", {}
        for name in PRESETS:
            theirs = Parameters.preset(name).to_dict()
            diff = {k: v for k, v in mine.items() if theirs[k] != v}
            if name == "default" or len(diff) < len(changes):
                nearest, changes = name, diff
        parts = [f"preset={nearest!r}", *(f"{k}={v!r}" for k, v in changes.items())]
        if self.return_iterations:
            parts.append("return_iterations=True")
        return ", ".join(parts)

    def get_extra_state(self) -> dict:
        """The parameters, so that ``state_dict()`` and ``load_state_dict()`` carry them.

        The module has no tensors of its own: its parameters are the method's settings.
        """
        return {
            "params": self.params.to_dict(),
            "return_iterations": self.return_iterations,
            "torchiid_version": __version__,
        }

    def set_extra_state(self, state: dict) -> None:
        """Restore what :meth:`get_extra_state` saved (a bad value is a ParameterError)."""
        if not isinstance(state, dict) or "params" not in state:
            raise ParameterError("this state was not saved by an IntrinsicDecomposer")
        self.params = _checked_params(Parameters.from_dict(dict(state["params"])))
        self.return_iterations = bool(state.get("return_iterations", False))
