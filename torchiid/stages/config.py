"""Configuration of the two stages: what each stage solves, with which weights and how.

Each stage takes three things:

* its **problem** — the tensors (:class:`ShadingProblem`, :class:`ReflectanceProblem`);
* its **weights** — one number per prior, 0 switches the prior off
  (:class:`ShadingWeights`, Eq. 1; :class:`ReflectanceWeights`, Eq. 12). The weights know
  their own step of the §3.4 schedule (:meth:`ShadingWeights.step`);
* its **options** — the priors' constants and the solver's settings
  (:class:`ShadingOptions`, :class:`ReflectanceOptions`).

:class:`~torchiid.params.Parameters` builds all four once (``params.shading_weights()``, ...),
so a parameter file, the ablation switches and the schedule have one path into the solvers.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from torchiid.core.exceptions import ParameterError
from torchiid.priors.reflectance_terms import COLOUR_WEIGHTS

__all__ = [
    "ShadingProblem",
    "ShadingWeights",
    "ShadingOptions",
    "ReflectanceProblem",
    "ReflectanceWeights",
    "ReflectanceOptions",
    "TemporalPrior",
    "TEMPORAL_NORMS",
]

#: the two forms of the temporal reflectance term (:class:`TemporalPrior`)
TEMPORAL_NORMS = ("l2", "l1")


def _check_tau(tau: float) -> None:
    if not tau > 0:
        raise ParameterError(f"the schedule's tau must be > 0, got {tau}")


def _nonnegative(obj: object) -> None:
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        value = getattr(obj, f.name)
        if not value >= 0:
            raise ParameterError(f"{type(obj).__name__}.{f.name} must be >= 0, got {value}")


@dataclass(frozen=True, eq=False)
class ShadingProblem:
    """The tensors of one shading solve (Eq. 1), linear RGB.

    Attributes:
        image: ``(B, 3, H, W)`` the image ``I`` (``>= 0``).
        patch_centers: ``(P, 2)`` or ``(B, P, 2)`` integer ``(y, x)`` patch centres for ``S_c``.
        patch_features: ``(B, P, D)`` patch descriptors ``f_b`` for ``S_c``.
        similarity: ``(B, 4, H, W)`` proposal similarities ``<g_i, g_j>`` on the 3x3 stencil
            for ``S_m``.
        base_image: ``(B, 3, H, W)`` the previous reflectance, from which the base of the
            matting Laplacian ``S_p`` is made (``ShadingOptions.base_mix``); ``None``: the
            Gaussian-smoothed image is the base.
        mask: ``(B, 1, H, W)`` bool region to decompose, or ``None``.

    A prior whose tensors are ``None`` is off whatever its weight.
    """

    image: torch.Tensor
    patch_centers: torch.Tensor | None = None
    patch_features: torch.Tensor | None = None
    similarity: torch.Tensor | None = None
    base_image: torch.Tensor | None = None
    mask: torch.Tensor | None = None

    def replace(self, **changes: object) -> ShadingProblem:
        """A copy with some tensors changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class ShadingWeights:
    """Weights of the shading priors (Eq. 1); 0 switches a prior off.

    Attributes:
        lambda_c: ``S_c``, the LLE constraints between similar patches (paper: ``λ_g``).
        lambda_p: ``S_p``, the matting-Laplacian propagation (paper: ``λ_g``).
        lambda_m: ``S_m``, the proposal affinity (``λ_m``).
        lambda_l: ``S_l``, the Retinex chromaticity term (``λ_l``).
        lambda_s: ``S_s``, plain shading smoothness (not in the paper; 0 is off).
    """

    lambda_c: float = 0.02
    lambda_p: float = 0.02
    lambda_m: float = 0.02
    lambda_l: float = 2.0
    lambda_s: float = 0.0

    def __post_init__(self) -> None:
        _nonnegative(self)

    @property
    def active(self) -> bool:
        """Whether any prior is on."""
        return any(getattr(self, f.name) > 0 for f in dataclasses.fields(self))

    def step(self, tau: float) -> ShadingWeights:
        """The next alternation's weights (§3.4): global and mid-level ``× τ``, local ``/ τ``.

        ``S_s`` is local and follows ``S_l``.
        """
        _check_tau(tau)
        return ShadingWeights(
            self.lambda_c * tau,
            self.lambda_p * tau,
            self.lambda_m * tau,
            self.lambda_l / tau,
            self.lambda_s / tau,
        )


@dataclass(frozen=True)
class ShadingOptions:
    """Constants of the shading priors and settings of their PCG solve.

    Attributes:
        t_c: chromaticity deviation of ``S_l`` (paper 1e-4, nearly binary).
        t_b: dark-pixel deviation of ``S_l`` (paper 0.05).
        t_i: intensity deviation of ``S_l`` (0: off, the paper's weights; see
            :func:`~torchiid.priors.shading_terms.retinex_weights`).
        t_e: colour-edge deviation of ``S_l`` (0: off, the paper's weights; see
            :func:`~torchiid.priors.shading_terms.edge_confidence`).
        t_d: brightness-step deviation of the same marks (0: off; see
            :func:`~torchiid.priors.shading_terms.edge_confidence`).
        t_h: stroke-height deviation of the same marks (0: off; the same function).
        t_m: deviation of ``S_m`` (paper 0.05).
        matting_eps: Levin's ε of ``S_p`` (1e-5).
        dark_eps: floor of intensities before logs.
        dark_level: with ``clip_level``, the pixel confidence of ``S_l``
            (:func:`~torchiid.priors.shading_terms.pixel_confidence`); both 0: off.
        clip_level: see ``dark_level``.
        base_sigma: Gaussian σ (px) of the default matting base image.
        base_mix: the previous reflectance's share of the matting base when one is given
            (alternations 2..k): the base is ``R^base_mix · I_σ^(1 − base_mix)`` (1: the
            paper's, ``R`` itself; see :func:`~torchiid.stages.shading.matting_base`).
        lle_k: LLE neighbours per patch (10).
        lle_reg: LLE Gram regulariser.
        lle_neighbours: ``"knn"`` or ``"random"`` (paper Table 2).
        seed: seed of random LLE neighbours.
        anchor: weight of the gauge-fixing anchor, relative to the mean diagonal.
        tol: PCG relative-residual tolerance.
        max_iter: PCG iteration cap of a cold solve (per coarse-to-fine level).
        warm_max_iter: PCG cap of a warm-started solve (0: ``max_iter``).
        levels: coarse-to-fine levels of a cold solve (1: none; not used with a multigrid
            preconditioner, which removes the smooth error itself).
        warn: emit ``ConvergenceWarning`` when a solve stops at its cap.
        preconditioner: ``"jacobi"`` (the inverse diagonal), ``"multigrid"`` (torch-only
            Galerkin multigrid V-cycle, :class:`~torchiid.solvers.multigrid.GalerkinMultigrid`,
            CPU or GPU: 10–15 iterations to 1e-4 where Jacobi needs 600–1500) or ``"amg"``
            (pyamg smoothed aggregation, CPU only). A multigrid hierarchy is built in the first
            alternation and reused by the later ones (kept in the :class:`ShadingSystemCache`);
            a reused hierarchy that has not converged after ``2 × (its fresh count) + 5``
            iterations is rebuilt and the solve goes on from where it stopped.
    """

    t_c: float = 1e-4
    t_b: float = 0.05
    t_i: float = 0.0
    t_e: float = 0.0
    t_d: float = 0.0
    t_h: float = 0.0
    t_m: float = 0.05
    matting_eps: float = 1e-5
    dark_eps: float = 1e-4
    dark_level: float = 0.0
    clip_level: float = 0.0
    base_sigma: float = 1.0
    base_mix: float = 1.0
    lle_k: int = 10
    lle_reg: float = 1e-3
    lle_neighbours: str = "knn"
    seed: int = 0
    anchor: float = 1e-8
    tol: float = 1e-4
    max_iter: int = 300
    warm_max_iter: int = 0
    levels: int = 5
    warn: bool = True
    preconditioner: str = "jacobi"

    def __post_init__(self) -> None:
        for name in ("t_i", "t_e", "t_d", "t_h"):
            if not getattr(self, name) >= 0:
                raise ParameterError(f"{name} must be >= 0 (0: off), got {getattr(self, name)}")
        if not 0 <= self.base_mix <= 1:
            raise ParameterError(f"base_mix must be in [0, 1], got {self.base_mix}")
        for name in ("anchor", "tol"):
            if not getattr(self, name) > 0:
                raise ParameterError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.levels < 1 or self.max_iter < 1 or self.warm_max_iter < 0:
            raise ParameterError(
                "levels and max_iter must be >= 1 and warm_max_iter >= 0, got "
                f"{self.levels}, {self.max_iter} and {self.warm_max_iter}"
            )
        if self.preconditioner not in ("jacobi", "multigrid", "amg"):
            raise ParameterError(
                "preconditioner must be 'jacobi', 'multigrid' or 'amg', "
                f"got {self.preconditioner!r}"
            )
        if self.lle_neighbours not in ("knn", "random"):
            raise ParameterError(
                f"lle_neighbours must be 'knn' or 'random', got {self.lle_neighbours!r}"
            )

    def replace(self, **changes: object) -> ShadingOptions:
        """A copy with some options changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class TemporalPrior:
    """A reflectance target from another frame of a video: Stage 2 pulls ``z`` toward it.

    Stage 2's energy (Eq. 12) gains a term on the pixels where the target is trusted:

    * ``norm="l2"`` (an anchor): ``s·γ_a·weight · Σ_i c_i ‖z_i − κ T_i‖²``;
    * ``norm="l1"`` (inside Split-Bregman, like ``A``, ``B``, ``C``):
      ``s·γ_a·weight · Σ_i c_i ‖z_i − κ T_i‖₁``,

    with ``c`` the confidence, ``s·γ_a`` the data term's weight (``value_scale · γ_a``, so the
    term follows the §3.4 schedule of the data term) and ``κ`` a global factor per image fitted
    to the current ``ρ`` (the median of ``Σ_c ρ / Σ_c T`` over the trusted pixels): the
    target's scale does not matter, as ``ρ``'s is arbitrary (with ``sigma > 0`` the target is
    ``ρ`` times the smoothed ratio instead, see ``sigma``). For the anchor, ``weight`` is
    the ratio of the anchor to the data term (``weight = 4``: without the sparsity terms
    ``z = (ρ + 4 κT) / 5``); for the L1 form, ``z`` snaps to ``κ T`` wherever
    ``|ρ − κT| ≤ weight / 2`` (per channel, without the sparsity terms) and follows ``ρ``
    beyond, so a wrong target (a flow error that passed the occlusion check, a new object)
    pulls with bounded force.

    Attributes:
        target: ``(B, 3, H, W)`` linear reflectance of the other frame, warped onto this one.
        confidence: ``(B, 1, H, W)`` in ``[0, 1]``: 1 where the target is trusted (the
            flow's forward–backward check passed), 0 where it is not (occluded, outside).
        weight: the term's weight relative to the data term, ``>= 0`` (0: off).
        norm: ``"l2"`` or ``"l1"``.
        sigma: ``0``: the target is ``κ T`` as it is. ``> 0``: only its levels are kept,
            smoothed over ``sigma`` px, and the detail is the current ``ρ``'s:
            ``ρ · exp(G_σ ∗ log(Σ_c T / Σ_c ρ))`` on the trusted pixels
            (:func:`~torchiid.stages.reflectance.temporal_term`). A warped target is blurred
            and shifted a little at its edges (resampling, flow error); frame after frame,
            that would accumulate.
    """

    target: torch.Tensor
    confidence: torch.Tensor
    weight: float = 4.0
    norm: str = "l2"
    sigma: float = 0.0

    def __post_init__(self) -> None:
        if self.norm not in TEMPORAL_NORMS:
            raise ParameterError(
                f"temporal norm must be one of {', '.join(TEMPORAL_NORMS)}, got {self.norm!r}"
            )
        if not self.weight >= 0:
            raise ParameterError(f"temporal weight must be >= 0, got {self.weight}")
        if not self.sigma >= 0:
            raise ParameterError(f"temporal sigma must be >= 0, got {self.sigma}")

    def replace(self, **changes: object) -> TemporalPrior:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class ReflectanceProblem:
    """The tensors of one reflectance solve (Eq. 12), linear RGB.

    Attributes:
        rho: ``(B, 3, H, W)`` the Stage 1 reflectance ``ρ = I / σ`` (``>= 0``).
        image: ``(B, 3, H, W)`` the image ``I``.
        gpca: ``(B, d, H, W)`` PCA-reduced proposal features ``g̊`` for ``B``.
        segments: ``(B, H, W)`` long segment labels giving the representatives of ``C``.
        mask: ``(B, 1, H, W)`` bool region to decompose, or ``None``.
        temporal: a :class:`TemporalPrior` (video: the previous frame's reflectance warped
            onto this one), or ``None`` (a still image: Eq. 12 unchanged).

    A prior whose tensors are ``None`` is off whatever its weight.
    """

    rho: torch.Tensor
    image: torch.Tensor
    gpca: torch.Tensor | None = None
    segments: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    temporal: TemporalPrior | None = None

    def replace(self, **changes: object) -> ReflectanceProblem:
        """A copy with some tensors changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class ReflectanceWeights:
    """Weights of the reflectance energy (Eq. 12); 0 switches a sparsity prior off.

    Attributes:
        gamma_l: local sparsity ``‖A z‖₁``.
        gamma_m: mid-level sparsity ``‖B z‖₁``.
        gamma_g: global sparsity ``‖C z‖₁``.
        gamma_a: the data term ``‖z − ρ‖²``.
    """

    gamma_l: float = 20.0
    gamma_m: float = 20.0
    gamma_g: float = 2.0
    gamma_a: float = 1.0

    def __post_init__(self) -> None:
        _nonnegative(self)

    @property
    def active(self) -> bool:
        """Whether any sparsity prior is on."""
        return self.gamma_l > 0 or self.gamma_m > 0 or self.gamma_g > 0

    def step(self, tau: float) -> ReflectanceWeights:
        """The next alternation's weights (§3.4): mid-level, global, data ``× τ``, local ``/ τ``."""
        _check_tau(tau)
        return ReflectanceWeights(
            self.gamma_l / tau, self.gamma_m * tau, self.gamma_g * tau, self.gamma_a * tau
        )


@dataclass(frozen=True)
class ReflectanceOptions:
    """Constants of the reflectance priors and settings of their Split-Bregman solve.

    Attributes:
        theta: Split-Bregman penalty ``θ``.
        value_scale: intensity unit the gammas and ``θ`` refer to (255: the paper's 8-bit
            values); the solver uses ``γ_a · value_scale`` and ``θ · value_scale`` on [0, 1].
        t: colour weight deviation of Eq. 7 on ``r̄``.
        t_g: deviation for ``g̊`` in ``B``'s weights (0: ``t``).
        window: side of the local window of ``A`` and ``B`` (paper: 11).
        colour_weights: scaling of ``r̄``: ``"bi"`` or ``"wide"``
            (:data:`~torchiid.priors.reflectance_terms.COLOUR_WEIGHTS`).
        luminance_weight: weight of ``L`` in ``r̄`` (``None``: that of ``colour_weights``).
        tol: relative change of ``z`` at which Split-Bregman stops.
        max_outer: Bregman iteration cap.
        cg_tol: CG tolerance of each ``z`` step.
        cg_max_iter: CG iteration cap of each ``z`` step.
        merge_stencil_terms: solve ``A`` and ``B`` as one exactly equivalent term.
        warm_state: start each solve's Bregman variable of the local term from the previous
            solve's on the same image (through the :class:`ReflectanceCache`), clipped to the
            new threshold: Split-Bregman is ADMM, which converges from any start, and the
            previous alternation's dual is close to the next one's.
        track_objective: record Eq. 12's value after every Bregman iteration.
        eps: floor of ``Σ_c R_c`` in the shading ratio.
        gap_tol: stop Split-Bregman when its relative duality gap (an upper bound on how far
            Eq. 12's objective is above its minimum, relatively) falls below this, measured
            at most every 5 iterations (sooner where the gap's rate predicts the tolerance);
            0: stop on the change of ``z`` (``tol``).
        theta_floor: with ``gap_tol``, residual balancing may lower ``θ`` down to ``θ ·
            theta_floor`` (1: a fixed ``θ``); a warm-started solve starts at the last solve's.
    """

    theta: float = 40.0
    value_scale: float = 255.0
    t: float = 0.05
    t_g: float = 0.0
    window: int = 11
    colour_weights: str = "bi"
    luminance_weight: float | None = None
    tol: float = 1e-3
    max_outer: int = 3
    cg_tol: float = 1e-3
    cg_max_iter: int = 5
    merge_stencil_terms: bool = True
    warm_state: bool = False
    track_objective: bool = True
    eps: float = 1e-4
    gap_tol: float = 0.0
    theta_floor: float = 1.0

    def __post_init__(self) -> None:
        if not self.gap_tol >= 0 or not 0 < self.theta_floor <= 1:
            raise ParameterError(
                f"need gap_tol >= 0 and 0 < theta_floor <= 1, got {self.gap_tol}, "
                f"{self.theta_floor}"
            )
        if not self.t > 0 or self.t_g < 0:
            raise ParameterError(f"deviations t > 0 and t_g >= 0 needed, got {self.t}, {self.t_g}")
        if self.window < 3 or self.window % 2 == 0:
            raise ParameterError(f"window must be odd and >= 3, got {self.window}")
        if self.colour_weights not in COLOUR_WEIGHTS:
            raise ParameterError(
                f"colour_weights must be one of {', '.join(COLOUR_WEIGHTS)}, "
                f"got {self.colour_weights!r}"
            )
        if self.luminance_weight is not None and self.luminance_weight < 0:
            raise ParameterError(f"luminance_weight must be >= 0, got {self.luminance_weight}")

    def replace(self, **changes: object) -> ReflectanceOptions:
        """A copy with some options changed."""
        return dataclasses.replace(self, **changes)
