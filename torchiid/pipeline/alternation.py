"""The alternations of Stage 1 and Stage 2 (paper §3.4), one step at a time.

:class:`Alternation` carries what passes from one step to the next: the previous shading (the
warm start of the next shading solve), the previous reflectance (the next matting base and
Split-Bregman start), the caches of the terms that do not change between alternations, and a
:class:`~torchiid.pipeline.results.SolveReport` per solve.
"""

from __future__ import annotations

import time
import warnings

import torch

from torchiid.core.exceptions import ConvergenceWarning
from torchiid.features.semantic import SemanticFeatures
from torchiid.params import Parameters, ReflectanceParameters, ShadingParameters
from torchiid.pipeline.inputs import WorkingInputs
from torchiid.pipeline.layers import gray_shading
from torchiid.pipeline.results import IterationLayers, SolveReport
from torchiid.priors.texture import texture_confidence
from torchiid.solvers.split_bregman import SplitBregmanResult
from torchiid.stages.reflectance import ReflectanceCache, solve_reflectance
from torchiid.stages.shading import ShadingDiagnostics, ShadingSystemCache, solve_shading

__all__ = [
    "Alternation",
    "texture_map",
    "shading_report",
    "reflectance_report",
    "warn_unconverged",
]


def texture_map(work: WorkingInputs, params: Parameters) -> torch.Tensor | None:
    """``S_l``'s texture confidence of ``work.image`` (``None``: ``t_x`` off, or no ``S_l``).

    The 1-px detection sees a different texture at every scale, so it is made once at the
    working resolution, and a coarse run takes it area-averaged.
    """
    o = params.shading
    if not (o.t_x > 0 and o.active and o.use_sl):
        return None
    return texture_confidence(work.image, o.t_x, work.mask, o.dark_eps, t_xc=o.t_xc)


class Alternation:
    """The alternations on one batch of images at one size.

    That size is the working resolution's, or the coarse size of :mod:`torchiid.pipeline.coarse`.

    Args:
        work: the inputs at that size.
        features: Stage 0's features of ``work.image``.
        params: the parameters (the stages' groups come from :meth:`Parameters.alternation`).
        keep_layers: keep every alternation's layers (:attr:`layers`).
        texture: ``S_l``'s texture confidence at this size (``None``: made from
            ``work.image`` when first needed, :func:`texture_map`).

    Attributes:
        sigma, rho: the last Stage 1 layers ``σ``, ``ρ = I / σ``.
        reflectance: the last Stage 2 reflectance ``R``.
        layers: every alternation's ``σ, ρ, R, S`` (with ``keep_layers``).
        solves: a :class:`~torchiid.pipeline.results.SolveReport` per solve.
        times: seconds per step (``"shading k"``, ``"reflectance k"``).
    """

    def __init__(
        self,
        work: WorkingInputs,
        features: SemanticFeatures,
        params: Parameters,
        keep_layers: bool = False,
        texture: torch.Tensor | None = None,
    ) -> None:
        self.work, self.features, self.params = work, features, params
        self.keep_layers = keep_layers
        self._texture = texture
        self.shading_cache = ShadingSystemCache()  # S_c, S_m, S_l, S_s are built once per image
        self.reflectance_cache = ReflectanceCache()  # and B's proposal-feature factor
        self.log_shading: torch.Tensor | None = None
        self.sigma: torch.Tensor | None = None
        self.rho: torch.Tensor | None = None
        self.reflectance: torch.Tensor | None = None
        self.layers: list[IterationLayers] = []
        self.solves: list[SolveReport] = []
        self.times: dict[str, float] = {}

    def texture(self) -> torch.Tensor | None:
        """``S_l``'s texture confidence at this size: the one given, else :func:`texture_map`."""
        if self._texture is None:
            self._texture = texture_map(self.work, self.params)
        return self._texture

    def shading_step(self, k: int, shading: ShadingParameters) -> None:
        """Stage 1 of alternation ``k`` (Eq. 1): ``σ`` and ``ρ = I / σ``.

        The matting base is made from the previous reflectance; the solve starts from the
        previous shading (or the warm start ``init``, or cold).
        """
        t0 = time.perf_counter()
        img, previous = self.work.image, self.reflectance
        if shading.active:
            problem = self.features.shading_problem(
                img, base_image=previous, mask=self.work.mask, texture=self.texture()
            )
            x0 = self.log_shading if self.log_shading is not None else self.work.log_shading0
            sh = solve_shading(
                problem, shading, x0=x0, cache=self.shading_cache, seed=self.params.seed,
                warn=False,
            )  # fmt: skip
            self.solves.append(shading_report(k, sh.diagnostics, shading, warm=x0 is not None))
            self.log_shading = sh.log_shading
            self.sigma, self.rho = sh.shading, sh.reflectance
        else:
            # baselines 2 and 3: no shading stage; Stage 2 flattens its own previous result
            self.rho = img if previous is None else previous
            self.sigma = gray_shading(img, self.rho, self.params.reflectance.shading_floor)
        self.times[f"shading {k}"] = time.perf_counter() - t0

    def release_shading_terms(self) -> None:
        """Let go of the kept shading terms and preconditioner (no later shading solve)."""
        self.shading_cache = ShadingSystemCache()

    def reflectance_step(self, k: int, reflectance: ReflectanceParameters) -> None:
        """Stage 2 of alternation ``k`` (Eq. 12): ``R`` from ``ρ``, by Split-Bregman.

        The solve starts from the previous reflectance (or the warm start's ``R0`` fitted to
        this ``ρ``, or ``ρ``).
        """
        t0 = time.perf_counter()
        img, rho = self.work.image, self.rho
        if reflectance.active:
            problem = self.features.reflectance_problem(rho, img, mask=self.work.mask)
            if self.work.temporal is not None:
                problem = problem.replace(temporal=self.work.temporal)
            self.reflectance_cache.last = k == self.params.iterations
            rr = solve_reflectance(
                problem, reflectance, z0=self._reflectance_start(), cache=self.reflectance_cache,
                track_objective=False,
            )  # fmt: skip
            refl = rr.reflectance
            self.solves.append(reflectance_report(k, rr.solver, reflectance))
        else:
            refl = rho
        self.times[f"reflectance {k}"] = time.perf_counter() - t0
        self.reflectance = refl
        if self.keep_layers:
            shading = gray_shading(img, refl, self.params.reflectance.shading_floor)
            self.layers.append(IterationLayers(self.sigma, rho, refl, shading))

    def _reflectance_start(self) -> torch.Tensor | None:
        """Split-Bregman's start: the previous ``R``, or ``R0`` on the scale of this ``ρ``."""
        z_init = self.work.reflectance0
        if self.reflectance is not None or z_init is None:
            return self.reflectance
        # R0 · S0 is ambiguous up to a factor: the least-squares fit of R0 to rho
        num = (self.rho * z_init).flatten(1).sum(1)
        den = z_init.square().flatten(1).sum(1)
        c = torch.where(den > 0, num / den.clamp_min(1e-30), 1.0)
        return z_init * c.view(-1, 1, 1, 1)


def shading_report(
    k: int, d: ShadingDiagnostics, shading: ShadingParameters, warm: bool
) -> SolveReport:
    """The report of alternation ``k``'s shading solve (``warm``: it had a start)."""
    cap = shading.cg_max_iter
    if warm:
        cap = shading.warm_cg_max_iter or shading.cg_max_iter
    residual = float(d.residual.max())
    return SolveReport("shading", k, d.iterations, 0, residual, shading.cg_tol, cap, d.converged)


def reflectance_report(
    k: int, sb: SplitBregmanResult, reflectance: ReflectanceParameters
) -> SolveReport:
    """The report of alternation ``k``'s Split-Bregman solve: its duality gap where measured."""
    o = reflectance
    value, tolerance, measure = float(sb.change.max()), o.bregman_tol, "relative change"
    distance = None
    if o.bregman_gap_tol > 0 and sb.gap is not None and bool(sb.gap.isfinite().all()):
        value, tolerance, measure = float(sb.gap.max()), o.bregman_gap_tol, "duality gap"
        if sb.distance is not None and bool(sb.distance.isfinite().all()):
            distance = float(sb.distance.max())
    return SolveReport(
        "reflectance", k, int(sb.outer_iterations.max()), sb.cg_iterations, value, tolerance,
        o.bregman_iter, bool(sb.converged.all()), measure, distance,
    )  # fmt: skip


def warn_unconverged(solves: list[SolveReport], stacklevel: int = 2) -> None:
    """A ``ConvergenceWarning`` when a solve stopped before its tolerance (``converge``)."""
    capped = [r for r in solves if not r.converged]
    if not capped:
        return
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
        stacklevel=stacklevel + 1,
    )
