"""The whole method (Saini & Narayanan, §3 and §3.4).

Stage 0 features, then k alternations of Stage 1 (L2 shading) and Stage 2 (L1 reflectance).

:func:`decompose` is the functional core and :class:`IntrinsicDecomposer` its ``nn.Module``
twin. Both take **linear** RGB ``(B, 3, H, W)`` tensors on any device and return a
:class:`Decomposition` whose layers satisfy ``image == reflectance * shading`` exactly (up to
floating-point rounding) inside the mask.

Scale: the product ``R · S`` is ambiguous up to a factor. The reflectance is returned as an
albedo in ``[0, 1]``: its ``albedo_quantile`` (0.999) quantile of the per-pixel maximum channel
is 1, and the few pixels above have their excess moved into the shading, which is gray, carries
the rest and may exceed 1 (see :func:`full_resolution_layers`).

Resolution: the method runs at a working resolution (``Parameters.max_side``, default 512 px
on the longer side); the shading is brought back to the input's resolution edge-aware and
``R = I / S`` there, band by band, so a 12-megapixel photo costs a few full-resolution layers.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from torchiid.core.check import as_mask, check_image
from torchiid.core.exceptions import (
    ConvergenceWarning,
    MemoryLimitError,
    ParameterError,
    ShapeError,
)
from torchiid.core.memory import MEMORY_LIMIT_VARIABLE, available_memory, memory_limit
from torchiid.core.stats import image_quantile, subgrid
from torchiid.features.semantic import SemanticFeatures, semantic_features
from torchiid.params import Parameters
from torchiid.priors.reflectance_terms import REPLAY_STEPS
from torchiid.priors.shading_terms import pixel_confidence
from torchiid.resample import GuidedUpsampler, downsample, row_bands, working_size
from torchiid.stages.config import TemporalPrior
from torchiid.stages.reflectance import ReflectanceCache, solve_reflectance
from torchiid.stages.shading import ShadingSystemCache, solve_shading

__all__ = [
    "Decomposition",
    "SolveReport",
    "FullLayers",
    "check_memory",
    "IterationLayers",
    "decompose",
    "full_resolution_layers",
    "IntrinsicDecomposer",
    "memory_needed",
]

#: Peak memory the method takes per pixel of the working resolution, on the CPU: the growth
#: of a ``torchiid decompose --max-side 0`` process's peak RSS above its own footprint (a
#: 128x96 photo), fitted on photos of 0.5 to 2 MP (``python tools/bench_memory.py``, stop
#: 33): about 1.29 KB per pixel in all with the ``default`` solvers (0.79, 1.59 and 2.73 GB
#: at 0.5, 1 and 2 MP), 2.04 KB when the Split-Bregman state is stored between updates, as
#: in the ``converged`` preset (1.02 and 2.03 GB at 0.5 and 1 MP: its 60-plane state per
#: channel and the multigrid hierarchy). Less the per-pixel cost of the full resolution below.
BYTES_PER_WORKING_PIXEL = {"replayed": 1240, "stored": 1990}
#: and per pixel of the input, beyond it: the photo, the layers and their bands
BYTES_PER_FULL_PIXEL = 50
#: and once per call: the features' and the solvers' own buffers
MEMORY_OVERHEAD = 150_000_000
#: the environment variable that switches the check off (``TORCHIID_MEMORY_CHECK=0``)
MEMORY_CHECK_VARIABLE = "TORCHIID_MEMORY_CHECK"


@dataclass(frozen=True)
class IterationLayers:
    """The layers of one alternation (paper Fig. 5), linear, at the working resolution.

    Each pair is in the output convention (albedo in ``[0, 1]``, see
    :func:`full_resolution_layers`).

    Attributes:
        sigma: ``(B, 1, h, w)`` Stage 1 shading ``σ``.
        rho: ``(B, 3, h, w)`` Stage 1 reflectance ``ρ = I / σ``.
        reflectance: ``(B, 3, h, w)`` Stage 2 reflectance ``R``.
        shading: ``(B, 1, h, w)`` Stage 2 shading ``S`` (gray ``I / R``).
    """

    sigma: torch.Tensor
    rho: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor


@dataclass(frozen=True)
class SolveReport:
    """What one stage's solver did in one alternation (the batch's worst image).

    Attributes:
        stage: ``"shading"`` (PCG on Eq. 1) or ``"reflectance"`` (Split-Bregman on Eq. 12).
        alternation: 1-based alternation.
        iterations: PCG iterations (shading) or outer Bregman iterations (reflectance).
        inner_iterations: CG iterations of all ``z`` steps (reflectance; 0 for shading).
        residual: final relative residual ``‖b − A s‖ / ‖b‖`` (shading) or last relative change
            of ``z`` (reflectance; with ``bregman_gap_tol``, its last relative duality gap).
        tolerance: the stopping tolerance of that measure.
        cap: the iteration cap (PCG iterations or Bregman iterations).
        converged: the measure fell below the tolerance before the cap.
        measure: what ``residual`` is: ``"residual"``, ``"relative change"`` or ``"duality
            gap"``.
        distance: with the duality gap, a certified bound on how far the reflectance ``z`` is
            from Eq. 12's exact minimiser ``z*``: ``‖z − z*‖ / ‖ρ‖`` (the batch's largest; see
            :class:`~torchiid.solvers.split_bregman.SplitBregmanResult`); ``None`` otherwise.
            A solve stopped at its cap was last measured one iterate before the one it
            returns, so its line does not print it.
    """

    stage: str
    alternation: int
    iterations: int
    inner_iterations: int
    residual: float
    tolerance: float
    cap: int
    converged: bool
    measure: str = "residual"
    distance: float | None = None

    @property
    def capped(self) -> bool:
        """Stopped at its iteration cap before its tolerance (raising the cap may help)."""
        return not self.converged and self.iterations >= self.cap

    def __str__(self) -> str:
        if self.converged:
            state = "converged"
        elif self.capped:
            state = f"stopped at its cap of {self.cap}"
        else:  # a breakdown or no further progress: a larger cap would not help
            state = f"stopped short of its tolerance before its cap of {self.cap} (no progress)"
        within = ""
        if self.distance is not None and self.converged:  # certified for the returned R
            within = f", R within {self.distance:.2%} of the minimiser"
        return (
            f"{self.stage} {self.alternation}: {self.iterations} iterations, "
            f"{self.measure} {self.residual:.2g} (tol {self.tolerance:g}){within}, {state}"
        )


@dataclass(frozen=True)
class Decomposition:
    """Result of :func:`decompose`; every layer is **linear** RGB / gray.

    Attributes:
        reflectance: ``(B, 3, H, W)`` final reflectance ``R``, an albedo in ``[0, 1]``
            (0 outside the mask), at the input's resolution.
        shading: ``(B, 1, H, W)`` final gray shading ``S`` (0 outside the mask), may exceed 1;
            ``reflectance * shading == image`` inside the mask.
        sigma: ``(B, 1, H, W)`` last Stage 1 shading ``σ`` (same convention as ``shading``),
            or ``None`` when ``decompose(..., return_stage1=False)``.
        rho: ``(B, 3, H, W)`` last Stage 1 reflectance ``ρ = I / σ`` in ``[0, 1]``, or
            ``None``.
        iterations: every alternation's layers if asked for, else an empty tuple.
        params: the parameters used.
        times: seconds per step (``"patch features"``, ``"proposals"``, ...,
            ``"shading k"``, ``"reflectance k"``, ``"total"``).
        mask: ``(B, 1, H, W)`` bool mask used, or ``None``.
        shading_white: ``(B,)`` the shading's ``params.view_quantile`` (0.99) quantile inside
            the mask: dividing ``shading`` by it gives a displayable image (the CLI's
            ``-shading.png``), and ``(R · shading_white, S / shading_white)`` is the other
            common convention (bright lit surfaces have shading 1).
        albedo_excess: ``(B,)`` fraction of the pixels inside the mask whose reflectance
            exceeded 1 and had the excess moved into the shading (at most
            ``1 - albedo_quantile`` on the sub-grid the quantile is taken on, so about that
            share of the full image).
        working_size: ``(h, w)`` the resolution the method ran at.
        solves: one :class:`SolveReport` per stage and alternation.
        features: the Stage 0 features used (at the working resolution) when
            ``decompose(..., return_features=True)``, else ``None``: pass them back as
            ``features=`` to skip Stage 0 (video reuses them across similar frames).
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
    sigma: torch.Tensor | None
    rho: torch.Tensor | None
    iterations: tuple[IterationLayers, ...]
    params: Parameters
    times: dict[str, float] = field(default_factory=dict)
    mask: torch.Tensor | None = None
    shading_white: torch.Tensor | None = None
    albedo_excess: torch.Tensor | None = None
    working_size: tuple[int, int] | None = None
    solves: tuple[SolveReport, ...] = ()
    features: SemanticFeatures | None = None

    @property
    def converged(self) -> bool:
        """Whether every solve reached its tolerance."""
        return all(r.converged for r in self.solves)


def _gray_shading(image: torch.Tensor, refl: torch.Tensor, floor: float) -> torch.Tensor:
    """Gray ``S = Σ_c I_c / Σ_c R_c`` (the least-squares-like gray ratio), floored."""
    s = image.sum(1, keepdim=True) / refl.sum(1, keepdim=True).clamp_min(floor)
    return s.clamp_min(floor)


def _final_shading(
    img: torch.Tensor, refl: torch.Tensor, sigma: torch.Tensor, params: Parameters
) -> torch.Tensor:
    """The working-resolution shading of the output: Stage 2's ``I / R`` where it is informed.

    In a dark pixel ``I ≈ 0``, so ``I / R`` is ≈ 0 whatever the light there: the shading
    would show every black object as an unlit hole. Where the pixel confidence ``c``
    (:func:`~torchiid.priors.shading_terms.pixel_confidence`) is below 1 the log-shading is
    blended toward Stage 1's ``σ``, which the confidence-aware ``S_l`` made a smooth
    continuation of the surroundings there: ``log S = c·log(I / R) + (1 − c)·log σ``.
    """
    s2 = _gray_shading(img, refl, params.shading_floor)
    if params.dark_level <= 0 and params.clip_level <= 0:
        return s2
    c = pixel_confidence(img, params.dark_level, params.clip_level)
    if bool((c >= 1).all()):
        return s2
    log_s = c * s2.log() + (1 - c) * sigma.clamp_min(params.shading_floor).log()
    return log_s.exp()


def _log_luminance(image: torch.Tensor, eps: float) -> torch.Tensor:
    y = 0.2126 * image[:, :1] + 0.7152 * image[:, 1:2] + 0.0722 * image[:, 2:3]
    return y.clamp_min(eps).log()


def _check_inputs(
    image: torch.Tensor, mask: torch.Tensor | None, params: Parameters
) -> tuple[torch.Tensor, torch.Tensor | None]:
    if not isinstance(image, torch.Tensor):
        raise ShapeError(
            f"expected image to be a torch.Tensor, got {type(image).__name__}; pass linear RGB "
            "as a float tensor of shape (B, 3, H, W) or (3, H, W), e.g. "
            "torch.from_numpy(rgb).permute(2, 0, 1).float() for an (H, W, 3) array, or read "
            "a file with torchiid.io.load_image(path).image"
        )
    for name, x in (("image", image), ("mask", mask)):
        if isinstance(x, torch.Tensor) and x.device.type == "meta":
            raise ShapeError(
                f"{name} is on the meta device (a tensor without values); pass a tensor that "
                "holds values, on the CPU or a GPU"
            )
    if image.dim() == 3:
        image = image[None]
    check_image(image, "image", min_side=params.patch_size)
    if mask is not None:
        mask = as_mask(mask, image, "mask")
        empty = ~mask.flatten(1).any(1)
        if bool(empty.any()):
            raise ShapeError(f"mask of image {int(empty.nonzero()[0])} is empty (no pixel inside)")
    return image, mask


def _warm_start(
    init: tuple[torch.Tensor, torch.Tensor],
    image: torch.Tensor,
    size: tuple[int, int],
    mask: torch.Tensor | None,
    params: Parameters,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(log S0, R0)`` of ``decompose(..., init=(R0, S0))`` at the working resolution."""
    if not isinstance(init, tuple | list) or len(init) != 2:
        raise ShapeError("init must be a pair (reflectance, shading) of tensors")
    r0, s0 = (torch.as_tensor(x).to(device=image.device, dtype=image.dtype) for x in init)
    r0 = r0[None] if r0.dim() == 3 else r0
    s0 = s0[None] if s0.dim() == 3 else s0
    b, _, big_h, big_w = image.shape
    if r0.dim() == 4 and tuple(r0.shape[-2:]) == tuple(size) and tuple(size) != (big_h, big_w):
        big_h, big_w = size  # given at the working resolution
    if tuple(r0.shape) != (b, 3, big_h, big_w):
        raise ShapeError(f"init reflectance must be {(b, 3, big_h, big_w)}, got {tuple(r0.shape)}")
    if (
        s0.dim() != 4
        or s0.shape[0] != b
        or s0.shape[1] not in (1, 3)
        or tuple(s0.shape[-2:]) != (big_h, big_w)
    ):
        raise ShapeError(f"init shading must be ({b}, 1, {big_h}, {big_w}), got {tuple(s0.shape)}")
    if not (torch.isfinite(r0).all() and torch.isfinite(s0).all()):
        raise ShapeError("init contains NaN or infinite values")
    s0 = downsample(s0.mean(1, keepdim=True), size).clamp_min(params.shading_floor).log()
    r0 = downsample(r0, size).clamp_min(0)
    if mask is not None:
        s0 = s0 * mask
    return s0.contiguous(), r0.contiguous()


def _temporal_prior(
    prior: TemporalPrior,
    image: torch.Tensor,
    size: tuple[int, int],
    mask: torch.Tensor | None,
) -> TemporalPrior:
    """The temporal prior of ``decompose(..., temporal=)`` at the working resolution."""
    if not isinstance(prior, TemporalPrior):
        raise ShapeError(
            f"temporal must be a torchiid.stages.TemporalPrior, got {type(prior).__name__}"
        )
    b, _, big_h, big_w = image.shape
    target = torch.as_tensor(prior.target).to(device=image.device, dtype=image.dtype)
    conf = torch.as_tensor(prior.confidence).to(device=image.device, dtype=image.dtype)
    target = target[None] if target.dim() == 3 else target
    conf = conf[None] if conf.dim() == 3 else conf
    if tuple(target.shape[-2:]) == tuple(size) and tuple(size) != (big_h, big_w):
        big_h, big_w = size  # given at the working resolution
    if tuple(target.shape) != (b, 3, big_h, big_w):
        raise ShapeError(
            f"temporal target must be {(b, 3, big_h, big_w)}, got {tuple(target.shape)}"
        )
    if tuple(conf.shape) != (b, 1, big_h, big_w):
        raise ShapeError(
            f"temporal confidence must be {(b, 1, big_h, big_w)}, got {tuple(conf.shape)}"
        )
    if not (torch.isfinite(target).all() and torch.isfinite(conf).all()):
        raise ShapeError("temporal target or confidence contains NaN or infinite values")
    conf = conf.clamp(0, 1)
    # confidence-weighted averages: untrusted target pixels do not leak into trusted ones
    weighted = downsample(target.clamp_min(0) * conf, size)
    conf = downsample(conf, size)
    target = weighted / conf.clamp_min(1e-6)
    if mask is not None:
        conf = conf * mask
    return prior.replace(target=target.contiguous(), confidence=conf.contiguous())


def memory_needed(
    height: int,
    width: int,
    params: Parameters | None = None,
    batch: int = 1,
    *,
    return_stage1: bool = False,
    return_iterations: bool = False,
) -> int:
    """Bytes a decomposition of ``batch`` images of ``height × width`` takes beyond what is loaded.

    An estimate of the peak growth on the CPU: :data:`BYTES_PER_WORKING_PIXEL` per pixel of
    the working resolution ``params.max_side``, :data:`BYTES_PER_FULL_PIXEL` per pixel of
    the input and :data:`MEMORY_OVERHEAD`, fitted on photos (README "Errors and exit
    statuses", "Memory": within 2% at full resolution with the ``default`` solvers, once 10%
    under; up to 16% over with ``converged``, up to 45% over at 512 px); with
    ``return_stage1`` (:func:`decompose`'s default) 16 bytes more per input pixel (``σ, ρ``
    at full resolution), with ``return_iterations`` 32 bytes per working pixel and
    alternation (``σ, ρ, R, S``). The libraries and the feature extractor, loaded once per
    process (about 0.5 GB), are not in it.
    """
    params = params if params is not None else Parameters.preset("default")
    h, w = working_size(height, width, params.max_side)
    stored = params.bregman_warm_state or params.bregman_iter > REPLAY_STEPS + 1
    per_working = BYTES_PER_WORKING_PIXEL["stored" if stored else "replayed"]
    if return_iterations:
        per_working += 32 * params.iterations
    per_full = BYTES_PER_FULL_PIXEL + (16 if return_stage1 else 0)
    return MEMORY_OVERHEAD + batch * (per_working * h * w + per_full * height * width)


def _gb(n: float) -> str:
    """Bytes as GB with two significant decimals below 10 GB (``0.25 GB``, ``31.2 GB``)."""
    return f"{n / 1e9:.2f} GB" if n < 10e9 else f"{n / 1e9:.1f} GB"


def check_memory(
    height: int,
    width: int,
    params: Parameters | None = None,
    batch: int = 1,
    *,
    limit: int | None = None,
    return_stage1: bool = False,
    return_iterations: bool = False,
) -> None:
    """Refuse, before any work, a CPU decomposition that cannot fit in the memory it may take.

    What it may take is what the machine has left (:func:`~torchiid.core.memory.available_memory`),
    or less: a cap the user set (``limit``, else ``TORCHIID_MEMORY_LIMIT`` in GB, see
    :func:`~torchiid.core.memory.memory_limit`). :func:`decompose` runs this check itself
    (without ``limit``); an application that holds a cap of its own calls it first with it.
    ``TORCHIID_MEMORY_CHECK=0`` switches off the comparison with what the machine has left; a
    cap the user set still holds.

    Args:
        height: the photo's height in pixels.
        width: its width.
        params: the parameters (their working resolution and solvers count).
        batch: images decomposed together.
        limit: a cap in bytes (``None``: ``TORCHIID_MEMORY_LIMIT``, if set).
        return_stage1: :func:`decompose` is asked to keep the Stage 1 layers.
        return_iterations: and every alternation's layers.

    Raises:
        MemoryLimitError: the estimate (:func:`memory_needed`) is over the cap or what is
            left; the message gives both figures and what to change.
        ParameterError: ``TORCHIID_MEMORY_LIMIT`` is not a number of GB.
    """
    params = params if params is not None else Parameters.preset("default")
    cap = memory_limit() if limit is None else limit
    flags = {"return_stage1": return_stage1, "return_iterations": return_iterations}
    need = memory_needed(height, width, params, batch, **flags)
    have = None
    switch = os.environ.get(MEMORY_CHECK_VARIABLE, "1").strip().lower()
    if switch not in ("0", "off", "false", "no"):
        try:
            have = available_memory()
        except Exception:  # noqa: BLE001 - the check must never be what breaks a decomposition
            have = None
    capped = cap is not None and (have is None or cap <= have)
    budget = cap if capped else have
    if budget is None or need <= budget:
        return
    h, w = working_size(height, width, params.max_side)
    where = "at full resolution" if (h, w) == (height, width) else f"at {w}x{h} px"
    many = f"{batch} images of " if batch > 1 else ""
    hint = ""
    default_side = Parameters().max_side
    if max(h, w) > default_side:
        at_default = params.replace(max_side=default_side)
        fit = memory_needed(height, width, at_default, batch, **flags)
        what = f"--max-side {default_side}, the default (max_side in Python)"
        if fit <= budget:
            hint = f"with {what}, it needs about {_gb(fit)}; "
        else:
            hint = f"even with {what}, it needs about {_gb(fit)}; "
    needs = f"decomposing {many}{width}x{height} px {where} needs about {_gb(need)} of memory"
    if capped:
        raise MemoryLimitError(
            f"{needs}, over the memory limit of {_gb(budget)}; {hint}raise the limit "
            f"(--memory-limit GB, or {MEMORY_LIMIT_VARIABLE}) to try it"
        )
    raise MemoryLimitError(
        f"{needs} and {_gb(have)} is available; {hint}set {MEMORY_CHECK_VARIABLE}=0 to try anyway"
    )


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
            ``[0, 1]``), sides of at least ``params.patch_size`` pixels. Images of a batch are
            solved together as one block-diagonal system.
        params: :class:`~torchiid.params.Parameters` (default: the ``default`` preset).
        mask: optional ``(B, 1, H, W)`` (or ``(H, W)``, ``(B, H, W)``) tensor, bool or numbers:
            nonzero is inside, as everywhere in torchiid (:func:`~torchiid.core.check.as_mask`);
            every prior is restricted to the pixels inside and the outside is returned as 0.
        features: precomputed Stage 0 features (at the working resolution), e.g. to run
            several parameter sets on one image.
        return_iterations: keep every alternation's ``σ, ρ, R, S`` (paper Fig. 5).
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
            ``params.warm_cg_max_iter`` like later alternations) and its Split-Bregman from
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
    t_start = time.perf_counter()
    image, mask = _check_inputs(image, mask, params)
    first = 1
    if schedule_start != 1:
        if not isinstance(schedule_start, int) or not 1 <= schedule_start <= params.iterations:
            raise ParameterError(
                f"schedule_start must be an alternation 1..{params.iterations}, "
                f"got {schedule_start!r}"
            )
        first = schedule_start
    in_dtype = image.dtype
    if in_dtype in (torch.float16, torch.bfloat16):
        image = image.float()
    big_h, big_w = image.shape[-2:]
    if image.device.type == "cpu":
        flags = {"return_stage1": return_stage1, "return_iterations": return_iterations}
        check_memory(big_h, big_w, params, image.shape[0], **flags)
    h, w = working_size(big_h, big_w, params.max_side)
    img = downsample(image, (h, w))
    msk = None
    if mask is not None:
        frac = downsample(mask.to(image.dtype), (h, w))
        msk = frac > 0.5
        tiny = ~msk.flatten(1).any(1)  # a small mask can vanish at the working resolution
        msk[tiny] = frac[tiny] > 0
        # the outside is blacked out so that it cannot influence any prior
        img = img * msk
    if min(h, w) < params.patch_size:
        raise ParameterError(
            f"working resolution {w}x{h} (max_side={params.max_side}) is smaller than the "
            f"{params.patch_size} px patches; raise max_side or lower patch_size"
        )
    if features is None:
        features = semantic_features(img, params)
    times = dict(features.times)
    run_total = params.iterations - first + 1  # the alternations this call runs
    if progress is not None:
        progress("features", 0, run_total)

    s_init = z_init = None
    if init is not None:
        s_init, z_init = _warm_start(init, image, (h, w), msk, params)
    temporal_low = None
    if temporal is not None:
        temporal_low = _temporal_prior(temporal, image, (h, w), msk)

    shading_w = params.shading_weights(first)
    refl_w = params.reflectance_weights(first)
    shading_opt, refl_opt = params.shading_options(), params.reflectance_options()
    s_prev = r_prev = None
    sigma = rho = refl = None
    shading_cache = ShadingSystemCache()  # S_c, S_m, S_l, S_s are built once per image
    reflectance_cache = ReflectanceCache()  # and B's proposal-feature factor
    layers: list[IterationLayers] = []
    solves: list[SolveReport] = []
    for k in range(first, params.iterations + 1):
        t0 = time.perf_counter()
        if shading_w.active:
            problem = features.shading_problem(img, base_image=r_prev, mask=msk)
            x0 = s_prev if s_prev is not None else s_init
            sh = solve_shading(problem, shading_w, shading_opt, x0=x0, cache=shading_cache)
            d = sh.diagnostics
            cap = shading_opt.max_iter
            if x0 is not None:
                cap = shading_opt.warm_max_iter or shading_opt.max_iter
            solves.append(
                SolveReport(
                    "shading", k, d.iterations, 0, float(d.residual.max()), shading_opt.tol, cap,
                    d.converged,
                )
            )  # fmt: skip
            s_prev = sh.log_shading
            sigma, rho = sh.shading, sh.reflectance
        else:
            # baseline 2/3: no shading stage; Stage 2 flattens its own previous result
            rho = img if r_prev is None else r_prev
            sigma = _gray_shading(img, rho, params.shading_floor)
        times[f"shading {k}"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if refl_w.active:
            problem = features.reflectance_problem(rho, img, mask=msk)
            if temporal_low is not None:
                problem = problem.replace(temporal=temporal_low)
            z0 = r_prev
            if z0 is None and z_init is not None:
                # the warm start on the scale of this rho (R0 · S0 is ambiguous up to a factor)
                num = (rho * z_init).flatten(1).sum(1)
                den = z_init.square().flatten(1).sum(1)
                c = torch.where(den > 0, num / den.clamp_min(1e-30), 1.0)
                z0 = z_init * c.view(-1, 1, 1, 1)
            rr = solve_reflectance(problem, refl_w, refl_opt, z0=z0, cache=reflectance_cache)
            refl = rr.reflectance
            sb = rr.solver
            value, tolerance, measure = float(sb.change.max()), refl_opt.tol, "relative change"
            distance = None
            if refl_opt.gap_tol > 0 and sb.gap is not None and bool(sb.gap.isfinite().all()):
                value, tolerance, measure = float(sb.gap.max()), refl_opt.gap_tol, "duality gap"
                if sb.distance is not None and bool(sb.distance.isfinite().all()):
                    distance = float(sb.distance.max())
            solves.append(
                SolveReport(
                    "reflectance", k, int(sb.outer_iterations.max()), sb.cg_iterations,
                    value, tolerance, refl_opt.max_outer, bool(sb.converged.all()), measure,
                    distance,
                )
            )  # fmt: skip
        else:
            refl = rho
        times[f"reflectance {k}"] = time.perf_counter() - t0
        r_prev = refl
        if return_iterations:
            shading = _gray_shading(img, refl, params.shading_floor)
            layers.append(IterationLayers(sigma, rho, refl, shading))
        # §3.4: strengthen mid-level, global and data terms, weaken local ones
        shading_w, refl_w = shading_w.step(params.tau), refl_w.step(params.tau)
        if progress is not None:
            progress("iteration", k - first + 1, run_total)

    capped = [r for r in solves if not r.converged]
    if params.converge and capped:
        worst = max(capped, key=lambda r: r.residual / r.tolerance)
        at_cap = sum(r.capped for r in capped)
        advice = []
        if at_cap:
            advice.append(f"{at_cap} at their safety caps: raise cg_max_iter / bregman_iter")
        if at_cap < len(capped):
            advice.append(
                f"{len(capped) - at_cap} could make no further progress (round-off or a solver "
                "breakdown, which larger caps would not change; the 'torchiid' logger at INFO "
                "level, or the CLI's --verbose, says which)"
            )
        warnings.warn(
            f"{len(capped)} of {len(solves)} solves stopped before their tolerance "
            f"(worst: {worst}); {'; '.join(advice)}",
            ConvergenceWarning,
            stacklevel=3,  # the caller of decompose (under torch's no_grad wrapper)
        )

    # final layers at full resolution: S brought up edge-aware, R = I / S, R an albedo in [0, 1]
    guide_low = _log_luminance(img, params.dark_eps)
    final = full_resolution_layers(
        image, _final_shading(img, refl, sigma, params), guide_low, mask, params
    )
    stage1 = None
    if return_stage1:
        stage1 = full_resolution_layers(image, sigma, guide_low, mask, params)
    if return_iterations:
        layers = [_normalised_iteration(img, it, msk, params) for it in layers]
    times["total"] = time.perf_counter() - t_start

    def back(x: torch.Tensor | None) -> torch.Tensor | None:
        return x if x is None or x.dtype == in_dtype else x.to(in_dtype)

    return Decomposition(
        reflectance=back(final.reflectance),
        shading=back(final.shading),
        sigma=None if stage1 is None else back(stage1.shading),
        rho=None if stage1 is None else back(stage1.reflectance),
        iterations=tuple(
            IterationLayers(
                *(back(getattr(it, n)) for n in ("sigma", "rho", "reflectance", "shading"))
            )
            for it in layers
        ),
        params=params,
        times=times,
        mask=mask,
        shading_white=final.shading_white,
        albedo_excess=final.albedo_excess,
        working_size=(h, w),
        solves=tuple(solves),
        features=features if return_features else None,
    )


@dataclass(frozen=True)
class FullLayers:
    """Full-resolution layers of one shading estimate (see :func:`full_resolution_layers`).

    Attributes:
        reflectance: ``(B, 3, H, W)`` albedo in ``[0, 1]``, 0 outside the mask.
        shading: ``(B, 1, H, W)`` gray shading (may exceed 1), 0 outside the mask.
        shading_white: ``(B,)`` the shading's ``params.view_quantile`` quantile inside the
            mask: the value shown as white in the viewable shading.
        albedo_excess: ``(B,)`` fraction of the pixels (inside the mask) whose reflectance
            exceeded 1 after the global scale and had the excess moved into the shading.
    """

    reflectance: torch.Tensor
    shading: torch.Tensor
    shading_white: torch.Tensor
    albedo_excess: torch.Tensor


def full_resolution_layers(
    image: torch.Tensor,
    shading_low: torch.Tensor,
    guide_low: torch.Tensor | None,
    mask: torch.Tensor | None,
    params: Parameters,
) -> FullLayers:
    """Full-resolution ``(R, S)`` from a shading solved at the working resolution.

    1. ``log S`` is upsampled by guided filtering with the full-resolution log-luminance as
       guide (:class:`~torchiid.resample.GuidedUpsampler`), band by band; at the working
       resolution itself it is used as it is.
    2. ``R = I / S``, so the reflectance keeps every full-resolution detail of the photo.
    3. **Scale convention** (``R · S`` is ambiguous up to a factor): the global factor makes
       the ``params.albedo_quantile`` quantile (default 0.999) of ``max_c R_c`` inside the
       mask equal to 1 — reflectance is an albedo in ``[0, 1]`` and the shading carries the
       rest (it may exceed 1: it is high dynamic range by nature). The few pixels above that
       quantile (specular highlights, light sources, noise in the dark) keep ``R ≤ 1`` by
       moving their excess ``max_c R_c`` into the shading, so ``R · S == I`` still holds
       exactly. A quantile rather than the maximum keeps one outlier from darkening the
       whole albedo.

    Args:
        image: ``(B, 3, H, W)`` full-resolution linear RGB.
        shading_low: ``(B, 1, h, w)`` positive shading at the working resolution.
        guide_low: ``(B, 1, h, w)`` log-luminance of the working-resolution image (unused,
            may be ``None``, when ``shading_low`` is at full resolution).
        mask: ``(B, 1, H, W)`` bool or ``None``; outside it both layers are 0.
        params: supplies ``albedo_quantile``, ``view_quantile``, ``dark_eps`` and the guided
            filter's ``guide_radius`` / ``guide_eps``.

    Returns:
        :class:`FullLayers`.
    """
    b, _, big_h, big_w = image.shape
    log_low = shading_low.clamp_min(params.shading_floor).log()
    shading = image.new_empty(b, 1, big_h, big_w)
    if tuple(log_low.shape[-2:]) == (big_h, big_w):
        torch.exp(log_low, out=shading)
    else:
        weight = None
        if mask is not None:  # the outside (blacked out, shading 1) must not enter the fits
            weight = downsample(mask.to(image.dtype), tuple(log_low.shape[-2:]))
        up = GuidedUpsampler(
            log_low, guide_low, (big_h, big_w), params.guide_radius, params.guide_eps, weight
        )
        for rows in row_bands(big_h, big_w):
            band = up.band(rows, _log_luminance(image[:, :, rows], params.dark_eps))
            shading[:, :, rows] = band.exp_()
    shading.clamp_min_(params.shading_floor)
    # global scale from a sub-grid (about a megapixel is plenty for a quantile)
    img_s, step = subgrid(image)
    peak_s = (img_s / shading[..., ::step, ::step]).amax(1, keepdim=True)
    msk_s = None if mask is None else mask[..., ::step, ::step]
    # "higher": at most a 1 - albedo_quantile share of the (sub-grid) pixels lies above k
    k = image_quantile(peak_s, params.albedo_quantile, msk_s, interpolation="higher")
    k = torch.where(k > 1e-12, k, torch.ones_like(k)).view(b, 1, 1, 1)  # black image: R = 0
    reflectance = image.new_empty(b, 3, big_h, big_w)
    moved = torch.zeros(b, device=image.device, dtype=torch.float64)
    for rows in row_bands(big_h, big_w):
        s_band = shading[:, :, rows].mul_(k)
        i_band = image[:, :, rows]
        excess = (i_band / s_band).amax(1, keepdim=True)
        over = excess > 1
        if mask is not None:
            over &= mask[:, :, rows]
        moved += over.flatten(1).sum(1)
        s_band.mul_(excess.clamp_min_(1))
        torch.div(i_band, s_band, out=reflectance[:, :, rows])
        reflectance[:, :, rows].clamp_(0, 1)  # R <= 1 already; removes 1 + 1 ulp
    if mask is not None:
        keep = mask.to(image.dtype)
        shading.mul_(keep)
        reflectance.mul_(keep)
        area = mask.flatten(1).sum(1).to(torch.float64)
    else:
        area = torch.full((b,), float(big_h * big_w), dtype=torch.float64, device=image.device)
    shade_s = shading[..., ::step, ::step]
    white = image_quantile(shade_s, params.view_quantile, msk_s)
    white = torch.where(white > 0, white, torch.ones_like(white))
    return FullLayers(reflectance, shading, white, (moved / area).to(torch.float32))


def _normalised_iteration(
    img: torch.Tensor, it: IterationLayers, msk: torch.Tensor | None, params: Parameters
) -> IterationLayers:
    """An alternation's layers in the output convention (albedos in [0, 1])."""
    guide = _log_luminance(img, params.dark_eps)
    st1 = full_resolution_layers(img, it.sigma, guide, msk, params)
    st2 = full_resolution_layers(img, it.shading, guide, msk, params)
    return IterationLayers(
        sigma=st1.shading, rho=st1.reflectance, reflectance=st2.reflectance, shading=st2.shading
    )


class IntrinsicDecomposer(nn.Module):
    """``nn.Module`` twin of :func:`decompose` for use inside larger models.

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
        self.params = params if params is not None else Parameters.preset("default")
        self.return_iterations = return_iterations

    def forward(self, image: torch.Tensor, mask: torch.Tensor | None = None) -> Decomposition:
        """Decompose ``image``; see :func:`decompose`."""
        return decompose(image, self.params, mask=mask, return_iterations=self.return_iterations)
