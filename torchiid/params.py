"""Parameters of the method, one frozen dataclass with named presets.

:class:`Parameters` holds every number and switch of the method. ``Parameters()`` is what
:func:`torchiid.decompose` does by default (the ``default`` preset); ``Parameters.preset("paper")``
gives the paper's values with the most thorough solver settings (§3.4 and Table 1).
:meth:`Parameters.to_json` / :meth:`Parameters.from_json` round-trip a parameter file, rejecting
unknown keys by name (a complete file written by an earlier version replays with the values
that version ran for the parameters added since, :data:`ADDED_SINCE`), and
:meth:`Parameters.variant` sets every switch of the paper's ablation variants v1–v7 (Table 3)
and baselines 1–3 (§5).

The stages do not read ``Parameters``: :meth:`Parameters.shading_weights`,
:meth:`~Parameters.shading_options`, :meth:`~Parameters.reflectance_weights` and
:meth:`~Parameters.reflectance_options` build their configuration objects
(:mod:`torchiid.stages.config`) in one place, switches included (a switched-off prior has
weight 0).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from torchiid.core.exceptions import ParameterError
from torchiid.stages.config import (
    ReflectanceOptions,
    ReflectanceWeights,
    ShadingOptions,
    ShadingWeights,
)

logger = logging.getLogger(__name__)

__all__ = ["Parameters", "PRESETS", "VARIANTS", "ADDED_SINCE"]


@dataclass(frozen=True)
class Parameters:
    """Every parameter of the decomposition.

    Stage 0 — semantic features:
        patch_size: side of the square patches described by the CNN (paper Table 1: 60 px).
        patch_stride: stride of the patch grid (paper Table 1: 30 px).
        feature_mode: ``"shared"`` (one CNN pass + RoI-align, fast) or ``"crop"`` (paper).
        feature_backend: ``"onnx"`` (onnxruntime) or ``"torch"``.
        lle_features: ``"cnn"`` (f_b) or ``"rgb"`` (patch mean colour), paper Table 2.
        lle_neighbours: ``"knn"`` or ``"random"``, paper Table 2 (p4 = cnn + knn).
        lle_k: neighbours per patch in the LLE constraints (paper: 10).
        lle_reg: Gram-matrix regulariser, ``C + lle_reg * tr(C) * I``.
        proposal_pca_dim: dimension of the PCA-reduced mid-level feature ``g̊`` (Stage 2).
        segment_scale: Felzenszwalb scale of the segments giving representative pixels ``Q``.
        seed: seed of every random choice (proposals ranking, random LLE neighbours).

    Stage 1 — shading (L2), Eq. 1:
        lambda_g: weight of the global terms ``S_c + S_p``.
        lambda_m: weight of the mid-level term ``S_m`` (paper and ``paper`` preset: 0.02;
            0.01 here, re-tuned with ``S_s`` on MIT-Berkeley).
        lambda_l: weight of the local Retinex term ``S_l``.
        lambda_s: weight of ``S_s``, plain 3x3 shading smoothness (not one of the paper's
            priors; the ``paper`` preset has 0, ``converged`` 0.003). Where ``S_l`` cuts the
            pairs across a chromaticity edge, the other terms decide only weakly whether the
            shading steps there; ``S_s`` pulls it towards continuity. Scheduled like
            ``lambda_l`` (``/ τ`` per alternation). Default 0.01 (MIT-Berkeley, README
            "Quality on MIT-Berkeley").
        t_c: chromaticity deviation of ``S_l``'s weights.
        t_b: dark-pixel deviation of ``S_l``'s weights.
        t_i: intensity deviation of ``S_l``'s weights (0: off, the paper's weights): pairs
            of the same chromaticity whose log-intensities differ by much more than ``t_i`` are
            not tied (dark print on a light ground of its own hue is not shading).
        t_e: colour-edge deviation of ``S_l``'s weights (0: off, the paper's weights): pairs
            touching a pixel beside a chromaticity edge (``1 - cos`` to a neighbour well
            above ``t_e``) are not tied, since such a pixel mixes two materials and its
            colour no longer names one (a bright print's anti-aliased rim would otherwise carry
            the print's brightness into the shading). See
            :func:`~torchiid.priors.shading_terms.edge_confidence`.
        t_d: brightness-step deviation of the same marks (0: off): pixels beside a step of
            log-intensity well above ``t_d`` are not tied either, so black text on white
            paper stays in the reflectance. A sharp step of one colour can also be a hard
            shadow's or a crease's edge, which then goes to the reflectance too (off in every
            preset; measured in the README).
        t_h: stroke-height deviation of the same marks (0: off): pixels on a dark or bright
            line at most 4 px wide (at the working resolution) whose log-intensity stands
            more than about ``t_h`` from its surroundings are not tied, so printed lettering
            stays in the reflectance while a shadow's or a crease's step does not count. 0.5
            in the ``print`` preset, for photos of documents, labels and packaging.
        t_m: deviation of ``S_m``'s weights on ``1 - <g_i, g_j>``.
        matting_eps: ε of the matting Laplacian (Levin et al.: 1e-5).
        dark_eps: intensities are clamped to at least this before taking logs.
        dark_level: pixels whose brightest channel is below this linear value (sRGB code 6.5
            at 0.002) carry no information about the shading: ``S_l`` asks for smooth shading
            there instead of copying their noise (confidence ramps to 1 at twice the level;
            0 turns it off). See :func:`~torchiid.priors.shading_terms.pixel_confidence`.
        clip_level: likewise for pixels with a channel at the ceiling of a low-dynamic-range
            image (linear value >= ``clip_level``, ramping in over the 0.03 below it); images
            with values above 1 have no ceiling. 0 turns it off.
        base_sigma: Gaussian σ (px) of the matting base image of the first alternation (the
            smoothed image; later alternations mix it with the previous reflectance,
            ``base_mix``).
        base_mix: the previous reflectance's share of the matting base of alternations
            2..k, a weighted geometric mean ``R^base_mix · I_σ^(1 − base_mix)`` with the
            smoothed image (1: the paper's, ``R`` alone, as in the ``paper`` preset). With
            ``R`` alone the matting term asks for flat shading wherever the reflectance is
            flat, and pushes the relief and bumps that the Retinex term gave to the
            shading into the reflectance at every later alternation. Default 0.5, 0.75 in
            the ``converged`` preset (MIT-Berkeley, README "Quality on MIT-Berkeley"). See
            :func:`~torchiid.stages.shading.matting_base`.
        anchor: weight of the gauge-fixing anchor ``α Σ (s_i − t)²``, relative to the mean
            diagonal of the system (only fixes the free constant; any tiny value gives the
            same shading).
        cg_tol: relative residual at which the shading PCG stops.
        cg_max_iter: cap on shading PCG iterations (per level of the first, coarse-to-fine
            solve).
        warm_cg_max_iter: cap on the shading PCG of alternations 2..k, which start from the
            previous alternation's shading (0: ``cg_max_iter``).
        coarse_levels: levels of the first, coarse-to-fine shading solve (1: none).
        shading_preconditioner: ``"jacobi"``, ``"multigrid"`` (torch Galerkin multigrid,
            converges in 10–15 iterations) or ``"amg"`` (pyamg, CPU); see
            :class:`~torchiid.stages.config.ShadingOptions`.

    Stage 2 — reflectance (L1), Eqs. 6–13:
        gamma_l: weight of the local sparsity term ``‖A z‖₁``.
        gamma_m: weight of the mid-level sparsity term ``‖B z‖₁``.
        gamma_g: weight of the global sparsity term ``‖C z‖₁``.
        gamma_a: weight of the data term ``‖z − ρ‖²``.
        theta: Split-Bregman penalty θ.
        value_scale: intensity unit of the gammas and θ (255: the paper's values are for
            Bi et al.'s 8-bit code; see :mod:`torchiid.stages.reflectance`).
        t: deviation of the reflectance weights ``v_ij`` (Eq. 7).
        t_g: deviation for ``g̊`` in ``B``'s weights (Eq. 9; 0: ``t``).
        window: side of the local window of ``A`` and ``B`` (paper: 11).
        colour_weights: scaling of the colour features ``r̄`` of ``v_ij``: ``"bi"`` (default:
            ``(0.5·L/100, a/36.7, b/36.7)``, at ``t = 0.05`` exactly the weight function of Bi
            et al.'s code, whose parameters the paper reuses) or ``"wide"``
            (``(0.1·L/100, a/220, b/220)``, an earlier reading with 5–6× wider weights under
            which the local term washes out thin texture and v7 loses to v4 on MIT); see
            :mod:`torchiid.priors.reflectance_terms`.
        luminance_weight: weight of ``L`` in ``r̄`` (``None``: that of ``colour_weights``,
            0.5 for ``"bi"``); larger values keep the local terms from merging neighbours that
            differ mainly in lightness (same-hue print on its background).
        bregman_iter: outer Split-Bregman iterations per stage.
        bregman_cg_iter: CG iterations of each Split-Bregman ``z`` step (an inexact solve; the
            Bregman updates absorb the error, Goldstein & Osher use one Gauss–Seidel sweep).
        bregman_tol: relative change of ``z`` at which Split-Bregman stops.
        bregman_gap_tol: relative duality gap at which Split-Bregman stops (measured at
            most every 5 iterations, sooner where its rate predicts the tolerance; a bound on
            how far Eq. 12's objective is above its minimum, relatively, or relative to a
            thousandth of ``γ_a ‖ρ‖²`` where the objective is smaller than that: nearly flat
            images); 0: stop on ``bregman_tol`` instead.
        bregman_theta_floor: with ``bregman_gap_tol``, residual balancing may lower the
            penalty ``θ`` to ``θ · bregman_theta_floor`` (1: a fixed ``θ``).
        bregman_cg_tol: relative residual at which each ``z`` step's CG stops.
        bregman_warm_state: start each alternation's Split-Bregman from the previous
            alternation's Bregman variable (the dual of the local term) instead of zero; the
            minimiser is the same, it is reached in fewer iterations.
        shading_floor: smallest shading value (and floor of ``Σ_c R_c`` in the gray-shading
            ratio); keeps ``R = I / S`` finite.

        converge: solve every stage to its tolerance: a solve that stops at its iteration cap
            (then a safety cap, not part of the method) raises a ``ConvergenceWarning`` from
            :func:`~torchiid.decompose`. ``False`` (the ``default`` preset): the caps are part
            of the preset (early-stopped solvers), the diagnostics still report them.

    Iterations, §3.4:
        iterations: alternations k of Stage 1 and Stage 2 (paper: 5).
        tau: after each iteration mid-level, global and data weights are multiplied by τ and
            local weights divided by τ (paper: 1.2).

    Switches (ablations): use_sc, use_sp, use_sm, use_sl, use_rl, use_rm, use_rg turn single
    priors on or off; ``stage1`` / ``stage2`` turn whole stages off (baselines 1 and 2).
    ``S_s`` (not one of the paper's priors) has no switch: it follows ``lambda_s`` (0 is off),
    so the variants of the ``default`` preset keep it; the paper's ablations as published are
    the variants of the ``paper`` preset.

    Working resolution and outputs:
        max_side: images whose longer side exceeds this are decomposed at this size and the
            layers brought back to full resolution edge-aware (0 = never resize). The default,
            512, was chosen by measurement (README: quality against working resolution on
            MIT-Berkeley, time and memory against photo size).
        guide_radius: box radius (working-resolution pixels) of the guided filter that
            upsamples the log-shading.
        guide_eps: regulariser of that guided filter (squared log-luminance units).
        albedo_quantile: the global scale makes this quantile of the per-pixel maximum
            reflectance channel equal to 1 (reflectance is an albedo in [0, 1]); pixels above
            it move their excess into the shading.
        view_quantile: quantile of the shading shown as white in the viewable shading PNG
            (the factor is recorded as ``shading_white``).
    """

    # Stage 0
    patch_size: int = 60
    patch_stride: int = 30
    feature_mode: str = "shared"
    feature_backend: str = "onnx"
    lle_features: str = "cnn"
    lle_neighbours: str = "knn"
    lle_k: int = 10
    lle_reg: float = 1e-3
    proposal_pca_dim: int = 8
    segment_scale: float = 200.0
    seed: int = 0
    # Stage 1
    lambda_g: float = 0.02
    lambda_m: float = 0.01
    lambda_l: float = 2.0
    lambda_s: float = 0.01
    t_c: float = 1e-4
    t_b: float = 0.05
    t_i: float = 0.0
    t_e: float = 0.015
    t_d: float = 0.0
    t_h: float = 0.0
    t_m: float = 0.05
    matting_eps: float = 1e-5
    dark_eps: float = 1e-4
    dark_level: float = 0.002
    clip_level: float = 0.99
    base_sigma: float = 1.0
    base_mix: float = 0.5
    anchor: float = 1e-8
    cg_tol: float = 1e-4
    cg_max_iter: int = 100
    warm_cg_max_iter: int = 30
    coarse_levels: int = 3
    shading_preconditioner: str = "jacobi"
    # Stage 2
    gamma_l: float = 20.0
    gamma_m: float = 20.0
    gamma_g: float = 2.0
    gamma_a: float = 1.0
    theta: float = 40.0
    value_scale: float = 255.0
    t: float = 0.05
    t_g: float = 0.0
    window: int = 11
    colour_weights: str = "bi"
    luminance_weight: float | None = None
    bregman_iter: int = 2
    bregman_cg_iter: int = 3
    bregman_tol: float = 1e-3
    bregman_gap_tol: float = 0.0
    bregman_theta_floor: float = 1.0
    bregman_cg_tol: float = 1e-3
    bregman_warm_state: bool = False
    shading_floor: float = 1e-4
    converge: bool = False
    # iterations
    iterations: int = 5
    tau: float = 1.2
    # switches
    use_sc: bool = True
    use_sp: bool = True
    use_sm: bool = True
    use_sl: bool = True
    use_rl: bool = True
    use_rm: bool = True
    use_rg: bool = True
    stage1: bool = True
    stage2: bool = True
    # working resolution and outputs
    max_side: int = 512
    guide_radius: int = 2
    guide_eps: float = 1e-3
    albedo_quantile: float = 0.999
    view_quantile: float = 0.99

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            want = f.type if isinstance(f.type, str) else f.type.__name__
            if want == "bool" and not isinstance(value, bool):
                raise ParameterError(f"parameter {f.name} must be true or false, got {value!r}")
            if want == "int" and (isinstance(value, bool) or not isinstance(value, int)):
                raise ParameterError(f"parameter {f.name} must be an integer, got {value!r}")
            if want == "float":
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise ParameterError(f"parameter {f.name} must be a number, got {value!r}")
                object.__setattr__(self, f.name, float(value))
        choices = {
            "feature_mode": ("shared", "crop"),
            "feature_backend": ("onnx", "torch"),
            "lle_features": ("cnn", "rgb"),
            "lle_neighbours": ("knn", "random"),
            "colour_weights": ("bi", "wide"),
            "shading_preconditioner": ("jacobi", "multigrid", "amg"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ParameterError(
                    f"parameter {name} must be one of {', '.join(allowed)}, "
                    f"got {getattr(self, name)!r}"
                )
        positive = [
            "patch_size",
            "patch_stride",
            "lle_k",
            "proposal_pca_dim",
            "iterations",
            "cg_max_iter",
            "bregman_iter",
            "bregman_cg_iter",
            "t_c",
            "t_b",
            "t_m",
            "t",
            "theta",
            "tau",
            "matting_eps",
            "dark_eps",
            "cg_tol",
            "bregman_tol",
            "segment_scale",
            "guide_radius",
            "guide_eps",
            "anchor",
            "coarse_levels",
            "value_scale",
            "bregman_cg_tol",
            "shading_floor",
            "window",
        ]
        for name in positive:
            if getattr(self, name) <= 0:
                raise ParameterError(f"parameter {name} must be > 0, got {getattr(self, name)}")
        nonneg = [
            "lambda_g",
            "lambda_m",
            "lambda_l",
            "lambda_s",
            "gamma_l",
            "gamma_m",
            "gamma_g",
            "gamma_a",
            "lle_reg",
            "max_side",
            "warm_cg_max_iter",
            "bregman_gap_tol",
            "dark_level",
            "clip_level",
            "base_sigma",
            "t_g",
            "t_i",
            "t_e",
            "t_d",
            "t_h",
        ]
        lw = self.luminance_weight
        if lw is not None:
            if isinstance(lw, bool) or not isinstance(lw, (int, float)) or not lw >= 0:
                raise ParameterError(
                    f"parameter luminance_weight must be a number >= 0 or null, got {lw!r}"
                )
            object.__setattr__(self, "luminance_weight", float(lw))
        for name in nonneg:
            if not getattr(self, name) >= 0:  # NaN too
                raise ParameterError(f"parameter {name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.base_mix <= 1:  # NaN too
            raise ParameterError(f"parameter base_mix must be in [0, 1], got {self.base_mix}")
        for name in ("albedo_quantile", "view_quantile", "bregman_theta_floor"):
            if not 0 < getattr(self, name) <= 1:
                raise ParameterError(
                    f"parameter {name} must be in (0, 1], got {getattr(self, name)}"
                )
        if self.patch_stride > self.patch_size:
            raise ParameterError(
                f"patch_stride ({self.patch_stride}) larger than patch_size ({self.patch_size}) "
                "leaves pixels uncovered"
            )
        if self.window % 2 == 0 or self.window < 3:
            raise ParameterError(f"parameter window must be odd and >= 3, got {self.window}")
        if not (self.stage1 or self.stage2):
            raise ParameterError("at least one of stage1 and stage2 must be on")

    # ------------------------------------------------------------------ construction
    @classmethod
    def preset(cls, name: str) -> Parameters:
        """A named parameter set: one of :data:`PRESETS` (default, print, paper, converged)."""
        if name not in PRESETS:
            raise ParameterError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        return cls(**PRESETS[name])

    def replace(self, **changes: Any) -> Parameters:
        """A copy with some fields changed (unknown names rejected)."""
        self._check_keys(changes)
        return dataclasses.replace(self, **changes)

    def variant(self, name: str) -> Parameters:
        """The paper's ablation variant (``v1``–``v7``, Table 3) or baseline (``baseline1``–3).

        ``v1``: S_l with all reflectance priors; ``v2``: + S_g; ``v3``: + S_m instead of S_g;
        ``v4``: all shading priors, R_l only; ``v5``: R_l + R_g; ``v6``: R_l + R_m; ``v7``: all.
        ``baseline1``: shading smoothness only (Stage 1, no Stage 2); ``baseline2``:
        reflectance sparsity only (Stage 2 on ρ = I); ``baseline3``: flattening as reflectance
        (Stage 2 local term only, on ρ = I).

        Every switch is set (the others of the variant are on), so
        ``p.variant("v4").variant("v7") == p.variant("v7")``.
        """
        if name not in VARIANTS:
            raise ParameterError(f"unknown variant {name!r}; choose one of {', '.join(VARIANTS)}")
        return dataclasses.replace(self, **{**_ALL_ON, **VARIANTS[name]})

    # ------------------------------------------------------------------ stage configuration
    def shading_weights(self, alternation: int = 1) -> ShadingWeights:
        """Stage 1's weights at ``alternation`` (1-based, §3.4 schedule), switches applied."""
        on = self.stage1
        w = ShadingWeights(
            lambda_c=self.lambda_g if on and self.use_sc else 0.0,
            lambda_p=self.lambda_g if on and self.use_sp else 0.0,
            lambda_m=self.lambda_m if on and self.use_sm else 0.0,
            lambda_l=self.lambda_l if on and self.use_sl else 0.0,
            lambda_s=self.lambda_s if on else 0.0,
        )
        for _ in range(alternation - 1):
            w = w.step(self.tau)
        return w

    def reflectance_weights(self, alternation: int = 1) -> ReflectanceWeights:
        """Stage 2's weights at ``alternation`` (1-based, §3.4 schedule), switches applied."""
        on = self.stage2
        w = ReflectanceWeights(
            gamma_l=self.gamma_l if on and self.use_rl else 0.0,
            gamma_m=self.gamma_m if on and self.use_rm else 0.0,
            gamma_g=self.gamma_g if on and self.use_rg else 0.0,
            gamma_a=self.gamma_a,
        )
        for _ in range(alternation - 1):
            w = w.step(self.tau)
        return w

    def shading_options(self) -> ShadingOptions:
        """Stage 1's prior constants and PCG settings (the pipeline reports, not warns)."""
        return ShadingOptions(
            t_c=self.t_c,
            t_b=self.t_b,
            t_i=self.t_i,
            t_e=self.t_e,
            t_d=self.t_d,
            t_h=self.t_h,
            t_m=self.t_m,
            matting_eps=self.matting_eps,
            dark_eps=self.dark_eps,
            dark_level=self.dark_level,
            clip_level=self.clip_level,
            base_sigma=self.base_sigma,
            base_mix=self.base_mix,
            lle_k=self.lle_k,
            lle_reg=self.lle_reg,
            lle_neighbours=self.lle_neighbours,
            seed=self.seed,
            anchor=self.anchor,
            tol=self.cg_tol,
            max_iter=self.cg_max_iter,
            warm_max_iter=self.warm_cg_max_iter,
            levels=self.coarse_levels,
            warn=False,
            preconditioner=self.shading_preconditioner,
        )

    def reflectance_options(self) -> ReflectanceOptions:
        """Stage 2's prior constants and Split-Bregman settings."""
        return ReflectanceOptions(
            theta=self.theta,
            value_scale=self.value_scale,
            t=self.t,
            t_g=self.t_g,
            window=self.window,
            colour_weights=self.colour_weights,
            luminance_weight=self.luminance_weight,
            tol=self.bregman_tol,
            max_outer=self.bregman_iter,
            cg_tol=self.bregman_cg_tol,
            cg_max_iter=self.bregman_cg_iter,
            warm_state=self.bregman_warm_state,
            gap_tol=self.bregman_gap_tol,
            theta_floor=self.bregman_theta_floor,
            track_objective=False,
            eps=self.shading_floor,
        )

    @staticmethod
    def _check_keys(data: dict[str, Any]) -> None:
        known = {f.name for f in fields(Parameters)}
        for key in data:
            if key not in known:
                raise ParameterError(f"Invalid parameter: {key}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Parameters:
        """Build from a mapping; unknown keys raise :class:`ParameterError` naming the key."""
        if not isinstance(data, dict):
            raise ParameterError(f"parameters must be a JSON object, got {type(data).__name__}")
        cls._check_keys(data)
        return cls(**data)

    def to_dict(self) -> dict[str, Any]:
        """All fields as a plain dict."""
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, path: str | os.PathLike, base: Parameters | None = None) -> Parameters:
        """Read a JSON file; keys it does not name keep the values of ``base`` (or defaults).

        A file that names every parameter except some of those added since the parameter set
        took its present shape (:data:`ADDED_SINCE`) is a complete record from an earlier version
        (as the CLI's ``-params.json``): those take the values that version ran, not
        ``base``'s, and a warning names them (a file written before ``base_mix`` existed
        replays the paper's matting base, ``base_mix`` 1, not the preset's mix).

        Raises:
            ParameterError: the file is missing or unreadable, not UTF-8 text, not a JSON
                object, or holds an unknown key, a value of the wrong type or a value out of
                range (also NaN or infinity); the one-line message names the file.
        """
        path = Path(path)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raise ParameterError(f"{path}: no such parameter file") from None
        except IsADirectoryError:
            raise ParameterError(f"{path}: is a directory, not a parameter file") from None
        except OSError as exc:
            why = exc.strerror or " ".join(str(exc).split())
            raise ParameterError(f"{path}: cannot read the parameter file ({why})") from None
        try:
            text = raw.decode("utf-8-sig")  # a byte-order mark, as some editors write, is fine
        except UnicodeDecodeError as exc:
            raise ParameterError(
                f"{path}: not a UTF-8 text file (byte 0x{raw[exc.start]:02x} at offset "
                f"{exc.start}); save the parameter file as UTF-8 JSON"
            ) from None

        def finite(value: str) -> float:
            number = float(value)
            if number in (float("inf"), float("-inf")):
                raise ValueError(f"{value} is out of range")
            return number

        def reject(name: str) -> None:
            raise ValueError(f"{name} is not a valid value")

        try:
            data = json.loads(text, parse_float=finite, parse_constant=reject)
        except (json.JSONDecodeError, ValueError, RecursionError) as exc:
            why = " ".join(str(exc).split()) or type(exc).__name__
            raise ParameterError(f"{path}: not a readable JSON file ({why})") from None
        if not isinstance(data, dict):
            kind = {list: "array", str: "string", bool: "true/false", type(None): "null"}
            raise ParameterError(
                f"{path}: expected a JSON object of parameters ({{...}}), got a JSON "
                f"{kind.get(type(data), 'number')}"
            )
        start = base.to_dict() if base is not None else {}
        try:
            cls._check_keys(data)
            older = _older_record(data)
            if older:
                logger.warning(
                    "%s: a parameter file from an earlier torchiid (it names every parameter "
                    "but %s); those take the values that version ran: %s (add them to the "
                    "file to choose others)",
                    path,
                    ", ".join(sorted(older)),
                    ", ".join(f"{k} {v!r}" for k, v in sorted(older.items())),
                )
                start.update(older)
            start.update(data)
            return cls(**start)
        except ParameterError as exc:
            raise ParameterError(f"{path}: {exc}") from None
        except (TypeError, ValueError, OverflowError) as exc:  # e.g. an integer beyond a float
            raise ParameterError(f"{path}: invalid parameter value ({exc})") from None

    def to_json(self, path: str | os.PathLike | None = None) -> str:
        """The parameters as JSON text; written to ``path`` (atomically) when given."""
        text = json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n"
        if path is not None:
            path = Path(path)
            tmp = path.with_name(f".{path.name}.tmp")
            try:
                tmp.write_text(text, encoding="utf-8")
                os.replace(tmp, path)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
        return text


#: Parameters added since the parameter set took its present shape (the architecture step:
#: older files lack other parameters too and count as partial), with the value that runs what
#: the method did before each existed (a switch off, the paper's choice). A file naming every
#: other parameter but not some of these is an earlier version's record. Each new parameter
#: must be added here with such a value (``tests/test_params.py`` checks that every parameter
#: is in the list or in the record of that step).
ADDED_SINCE: dict[str, Any] = {
    "shading_preconditioner": "jacobi",
    "t_i": 0.0,
    "converge": False,
    "bregman_warm_state": False,
    "luminance_weight": None,
    "lambda_s": 0.0,
    "t_e": 0.0,
    "t_d": 0.0,
    "t_h": 0.0,
    "bregman_gap_tol": 0.0,
    "bregman_theta_floor": 1.0,
    "base_mix": 1.0,
}


def _older_record(data: dict[str, Any]) -> dict[str, Any]:
    """The :data:`ADDED_SINCE` values for a complete record from an earlier version, or ``{}``.

    Complete: it names every parameter that is not in :data:`ADDED_SINCE` (so it is no
    partial set of overrides) and leaves out at least one that is.
    """
    missing = {f.name for f in fields(Parameters)} - set(data)
    if not missing or not missing <= ADDED_SINCE.keys():
        return {}
    return {k: ADDED_SINCE[k] for k in missing}


#: Named parameter sets. ``default`` (= ``Parameters()``): tuned on the MIT-Berkeley objects for
#: quality and speed. The first shading solve (coarse to fine) is capped at 100 PCG iterations
#: per level and the later, warm-started ones at 30; the Split-Bregman stage runs 2 outer
#: iterations of 3 CG steps (an inexact, early-stopped L1 solve: more iterations flatten further
#: and scored worse on MIT and on noisy synthetic Mondrians). Its shading energy adds plain
#: smoothness ``S_s`` (``lambda_s`` 0.01) and halves ``lambda_m`` (0.01): MIT 0.0220 -> 0.0211;
#: ``S_l`` does not tie pixels beside a colour edge (``t_e`` 0.015, stop 23): 0.0211 -> 0.0203;
#: the matting base of alternations 2-5 mixes in the smoothed image (``base_mix`` 0.5, stop 31):
#: 0.0203 -> 0.0201.
#: ``paper``: the paper's energy (``lambda_m`` 0.02, no ``S_s``, no ``t_e``) with the solvers at
#: their most thorough (300 PCG iterations, 4 x 5 Split-Bregman steps). The paper's other values
#: (§4: λ_g, λ_l, γ, θ, τ, t, k = 5, 60/30 px patches) are in both. Mean LMSE in the README.
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    # printed matter (documents, labels, packaging, posters): S_l does not tie pixels on thin
    # strokes either (t_h 0.5), so black text on white paper stays in the reflectance (stop 23,
    # tools/print_check.py: ink/paper reflectance 0.996 -> 0.168, true 0.036). Thin grooves and
    # fine texture go to the reflectance too: MIT 0.0203 -> 0.0221 (teabag2 0.0186 -> 0.0125);
    # 0.0218 with the default's base_mix of stop 31.
    "print": {"t_h": 0.5},
    "paper": {
        "base_mix": 1.0,
        "lambda_m": 0.02,
        "lambda_s": 0.0,
        "t_e": 0.0,
        "cg_max_iter": 300,
        "warm_cg_max_iter": 0,
        "bregman_iter": 4,
        "bregman_cg_iter": 5,
    },
    # every solve to its tolerance (README "Solving to tolerance"): the shading by multigrid
    # PCG to a relative residual of 1e-4 (Jacobi takes over where the multigrid stagnates),
    # Split-Bregman until its duality gap is below 0.5% (stop 28, below; before, until z changed
    # by less than 5e-5 per iteration). theta is only the splitting penalty (the minimiser
    # does not depend on it): 2.5 gets there in ~80 iterations where the paper's 40 needs ~350.
    # Each alternation's Split-Bregman starts from the previous one's Bregman variable (same
    # minimiser, 10-45% fewer iterations in alternations 2-5). The caps are safety caps (a
    # ConvergenceWarning if hit). 7.8-23.7 s per 512 px photo on 2 CPU cores (stop 33, six
    # skimage photos, tools/bregman_iterations.py).
    # Re-tuned for converged solves (MIT, README "Solving to tolerance"): tau 1.1 (each
    # alternation reaches its minimum, so the weight drift compounds; 0.0234 -> 0.0229, 7 of 10
    # objects better) and the L1 weights gamma halved (a minimiser flattens fully where early
    # stopping did not; 0.0229 -> 0.0226, 7 of 10 better; a quarter: 0.0225, 5 of 10).
    # Then the shading priors (stop 20): t_i 1.0 (S_l no longer ties same-hue neighbours whose
    # brightness differs by much more than e-fold, i.e. print: teabag2 0.0274 -> 0.0218) with
    # lambda_m halved (S_m alone at half: mean unchanged, 8 of 10 objects better): 0.0226 ->
    # 0.0221, 7 of 10 better.
    "converged": {
        "converge": True,
        "shading_preconditioner": "multigrid",
        "cg_max_iter": 3000,
        "warm_cg_max_iter": 0,
        "theta": 2.5,
        "bregman_iter": 400,
        "bregman_cg_iter": 5,
        "bregman_tol": 5e-5,
        # Stop 28: Split-Bregman stops on its duality gap, 0.5% (Eq. 12's objective provably
        # within 0.5% of its minimum, or of 1e-3 γ_a‖ρ‖² on nearly flat images whose minimum
        # is smaller than that; the change rule above, 5e-5, remains for terms that
        # cannot measure the gap, e.g. video's temporal term), and residual balancing may
        # lower theta to a quarter: ten photos 2031 -> 1265 Bregman iterations, MIT unchanged.
        "bregman_gap_tol": 0.005,
        "bregman_theta_floor": 0.25,
        "bregman_cg_tol": 1e-6,
        "bregman_warm_state": True,
        "tau": 1.1,
        "gamma_l": 10.0,
        "gamma_m": 10.0,
        "gamma_g": 1.0,
        # Stop 23: S_l does not tie pixels beside a colour edge (t_e 0.015, as in the default),
        # with t_i 1.5 in place of 1.0: 0.02172 -> 0.02125, 9 of 10 objects better (apple
        # worse by 0.00002). t_e alone (t_i 1.0): 0.0213, 5 of 10; with t_i 0: 0.0214, 7 of 10
        # but teabag2's print worse (0.0213 -> 0.0234); t_i 2.0: 0.0213, 7 of 10.
        "t_i": 1.5,
        # Stop 31: the matting base of alternations 2-5 mixes the previous reflectance with the
        # smoothed image (README "Quality on MIT-Berkeley"): base_mix 0.75, 0.02127 -> 0.02073,
        # 7 of 10 objects better (0.5: 0.02071, 6 of 10, and worse than 0.75 on 6 of 10). Then
        # t_e 0.0075 (more mixed pixels beside colour edges cut): 0.02073 -> 0.02021, 6 of 10
        # better, teabag2's print 0.0226 -> 0.0197 (t_e 0.01: 0.02041, 6 of 10).
        "base_mix": 0.75,
        "t_e": 0.0075,
        # Then Levin's epsilon of S_p (the paper's 1e-5): 3e-4, 0.02021 -> 0.01991, 6 of 10
        # better (1e-3: 0.01983, 5 of 10). In a window whose base varies by less than about
        # sqrt(epsilon) the matting term asks for constant shading; the mixed base carries the
        # image's faint variation (noise, fine texture), which S_p at 1e-5 let the converged
        # shading follow. The early-stopped default is worse with it (base_mix 0.75, 1e-4:
        # 0.02034, 3e-4: 0.02053, against 0.02015) and keeps 1e-5.
        "matting_eps": 3e-4,
        # Stop 21: a weak S_s (lambda_s 0.003, a third of the default's) with S_m's weight halved
        # again (lambda_m 0.005): 0.02208 -> 0.02171, 8 of 10 objects better. Solved to the
        # minimum, S_m (weights near 1 inside a proposal) flattens the shading across an
        # object's curved surfaces; the uniform, weaker S_s keeps the level across chromaticity
        # edges without that. Either change alone does less: S_s 0.01 / 0.003 / 0.001 with
        # lambda_m 0.01 scored 0.02205 / 0.02187 / 0.02197 (5, 5, 6 of 10 better), lambda_m
        # 0.005 alone 0.02217, S_s 0.003 without S_m 0.02207.
        "lambda_m": 0.005,
        "lambda_s": 0.003,
    },
}

_ALL_ON: dict[str, Any] = {
    "use_sc": True,
    "use_sp": True,
    "use_sm": True,
    "use_sl": True,
    "use_rl": True,
    "use_rm": True,
    "use_rg": True,
    "stage1": True,
    "stage2": True,
}
VARIANTS: dict[str, dict[str, Any]] = {
    "v1": {"use_sc": False, "use_sp": False, "use_sm": False},
    "v2": {"use_sm": False},
    "v3": {"use_sc": False, "use_sp": False},
    "v4": {"use_rm": False, "use_rg": False},
    "v5": {"use_rm": False},
    "v6": {"use_rg": False},
    "v7": {},
    "baseline1": {"stage2": False},
    "baseline2": {"stage1": False},
    "baseline3": {"stage1": False, "use_rm": False, "use_rg": False},
}
