"""The parameter group of Stage 1, the L2 shading solve (paper §3.2, Eq. 1)."""

import dataclasses

from torchiid.params.fields import SCHEDULE_DOWN, SCHEDULE_UP, StageGroup, param, switch

__all__ = ["ShadingParameters"]


@dataclasses.dataclass(frozen=True)
class ShadingParameters(StageGroup):
    """Stage 1: the weights and constants of the shading priors, their switches, the PCG solve.

    :func:`~torchiid.stages.shading.solve_shading` takes this group as it is; at alternation
    ``k`` the weights are those of :meth:`~torchiid.params.Parameters.alternation` (§3.4).
    :meth:`weights` gives each prior's weight, 0 where a switch turns it off. ``S_s`` (plain
    smoothness, not one of the paper's priors) has no switch: ``lambda_s = 0`` (the default) is off,
    so the ablation variants of the ``converged`` preset keep it.

    The confidence marks of ``S_l`` (``t_i``, ``t_e``, ``t_d``, ``t_h``, ``t_x``; 0 is off,
    the paper's weights) untie pixel pairs whose colour does not name one material; see
    :func:`~torchiid.priors.shading_terms.retinex_weights` and
    :func:`~torchiid.priors.shading_terms.edge_confidence` and
    :func:`~torchiid.priors.texture.detexture`.
    """

    lambda_g: float = param(
        0.02,
        "weight of the global terms S_c + S_p",
        paper=0.02,
        valid=">= 0",
        schedule=SCHEDULE_UP,
    )
    lambda_m: float = param(
        0.02,
        "weight of the mid-level term S_m",
        paper=0.02,
        valid=">= 0",
        schedule=SCHEDULE_UP,
    )
    lambda_l: float = param(
        2.0,
        "weight of the local Retinex term S_l",
        paper=2.0,
        valid=">= 0",
        schedule=SCHEDULE_DOWN,
    )
    lambda_s: float = param(
        0.0,
        "weight of S_s, plain 3x3 shading smoothness (not one of the paper's priors; 0: off; "
        "0.003 in the converged preset)",
        paper=0.0,
        valid=">= 0",
        schedule=SCHEDULE_DOWN,
    )
    t_c: float = param(1e-4, "chromaticity deviation of S_l's weights", paper=1e-4, valid="> 0")
    t_b: float = param(0.05, "dark-pixel deviation of S_l's weights", paper=0.05, valid="> 0")
    t_i: float = param(
        0.0,
        "intensity deviation of S_l's weights: same-chromaticity pairs whose log-intensities "
        "differ by much more are not tied (0: off)",
        paper=0.0,
        valid=">= 0",
    )
    t_e: float = param(
        0.015,
        "colour-edge deviation of S_l's weights: pixels beside a chromaticity edge (1 - cos "
        "to a neighbour well above t_e) are not tied (0: off)",
        paper=0.0,
        valid=">= 0",
        why="0.015: such a pixel mixes two materials and its colour names neither; at the "
        "paper's 0 the 5-fold validation LMSE is 0.00123 worse (paired spread 0.00069)",
    )
    t_d: float = param(
        0.0,
        "brightness-step deviation of the same marks: pixels beside a step of log-intensity "
        "well above t_d are not tied (0: off)",
        paper=0.0,
        valid=">= 0",
    )
    t_h: float = param(
        0.0,
        "stroke-height deviation of the same marks: pixels on a line at most 4 px wide "
        "standing more than about t_h in log-intensity from its surroundings are not tied "
        "(0: off; 0.5 in the print preset)",
        paper=0.0,
        valid=">= 0",
    )
    t_x: float = param(
        0.02,
        "texture deviation of S_l: where the image is densely textured (median fine-scale "
        "residual of log-intensity well above t_x), S_l takes its targets from the image "
        "without its fine texture, so the texture stays in the reflectance (0: off, as in "
        "the paper, print and converged presets)",
        paper=0.0,
        valid=">= 0",
        why="0.02 with t_xc: texture in the synthetic planes' shading 0.626 -> 0.337, in "
        "coffee's wood grain 0.605 -> 0.437; MIT 0.0003 worse",
    )
    t_xc: float = param(
        0.02,
        "colour slope of texture: with t_x, only fine texture whose chromaticity changes "
        "with its lightness by more than about t_xc per unit of log-intensity counts, away "
        "from colour edges (0: all dense texture, the texture preset)",
        paper=None,
        valid=">= 0",
        why="0.02: above the 1.3% colour slope of the synthetic tiles, seen only as they are "
        "noiseless (0.01: 0.285, 0.02: 0.337, 0.03: 0.355 of their texture)",
    )
    t_x_sigma: float = param(
        5.0,  # torchiid.priors.texture.REMOVAL_SIGMA (a test keeps them equal; no torch here)
        "scale (px) of the local linear fit whose residual S_l's targets lose where t_x finds "
        "texture: grain up to about 2.5·t_x_sigma px apart leaves them, light that bends more "
        "slowly stays (only with t_x > 0)",
        paper=None,
        valid="> 0",
        why="5: wood's rings, about 9 px apart, leave the targets (a 3-px fit keeps a tenth of "
        "them), while a hard shadow edge across the texture blurs less than at 8 px",
    )
    t_m: float = param(
        0.05, "deviation of S_m's weights on 1 - <g_i, g_j>", paper=0.05, valid="> 0"
    )
    matting_eps: float = param(
        1e-5, "ε of the matting Laplacian of S_p (Levin et al.'s value)", valid="> 0"
    )
    dark_eps: float = param(
        1e-4, "intensities are clamped to at least this before taking logs", valid="> 0"
    )
    dark_level: float = param(
        0.002,
        "pixels whose brightest channel is below this linear value carry no information about "
        "the shading: S_l asks for smooth shading there (confidence 1 at twice it; 0: off)",
        paper=0.0,
        valid=">= 0",
        why="an input guard, not a tuned weight: black pixels otherwise get noisy or zero "
        "shading; the MIT objects have none (off: -0.00013 in validation)",
    )
    clip_level: float = param(
        0.99,
        "likewise for pixels with a channel at or above this linear value in an image without "
        "values above 1 (ramping in over the 0.03 below it; 0: off)",
        paper=0.0,
        valid=">= 0",
        why="an input guard for clipped highlights, which the MIT objects hardly have "
        "(off: +0.000003 in validation)",
    )
    base_sigma: float = param(
        1.0,
        "Gaussian σ (px) of the smoothed image, the matting base of the first alternation",
        valid=">= 0",
    )
    base_mix: float = param(
        0.5,
        "the previous reflectance's share of the matting base of alternations 2..k, "
        "R^base_mix · I_σ^(1 - base_mix) (1: R alone)",
        paper=1.0,
        valid="in [0, 1]",
        why="0.5: the smoothed image in the matting base keeps relief in the shading; at the "
        "paper's 1 the 5-fold validation LMSE is 0.00038 worse (paired spread 0.00028)",
    )
    lle_k: int = param(
        10, "neighbours per patch in the LLE constraints of S_c", paper=10, valid="> 0"
    )
    lle_reg: float = param(
        1e-3, "regulariser of the LLE Gram matrix, C + lle_reg · tr(C) · I", valid=">= 0"
    )
    lle_neighbours: str = param(
        "knn",
        "the patches each LLE constraint combines: 'knn' (nearest in f_b) or 'random' (Table 2)",
        paper="knn",
        valid="one of knn, random",
    )
    anchor: float = param(
        1e-8,
        "weight of the gauge-fixing anchor α Σ (s_i - t)², relative to the mean diagonal "
        "(it fixes only the free constant)",
        valid="> 0",
    )
    cg_tol: float = param(1e-4, "relative residual at which the shading PCG stops", valid="> 0")
    cg_max_iter: int = param(
        100,
        "cap on the PCG iterations of a shading solve (per level of the first, coarse-to-fine "
        "solve)",
        valid="> 0",
        why="100: an early-stopped solve, tuned with the other caps on MIT-Berkeley for "
        "quality and speed (paper preset: 300)",
    )
    warm_cg_max_iter: int = param(
        30,
        "cap on the PCG iterations of the warm-started solves of alternations 2..k "
        "(0: cg_max_iter)",
        valid=">= 0",
        why="30: likewise (paper preset: 0, the cold cap)",
    )
    coarse_levels: int = param(
        3, "levels of the first, coarse-to-fine shading solve (1: none)", valid="> 0"
    )
    shading_preconditioner: str = param(
        "jacobi",
        "'jacobi', 'multigrid' (torch Galerkin multigrid, 10-15 iterations to 1e-4) or "
        "'amg' (pyamg, CPU)",
        valid="one of jacobi, multigrid, amg",
    )
    use_sc: bool = switch("S_c")
    use_sp: bool = switch("S_p")
    use_sm: bool = switch("S_m")
    use_sl: bool = switch("S_l")
    stage1: bool = switch("the whole stage", "off: baselines 2 and 3")

    #: the priors of :meth:`weights`; ``S_c`` and ``S_p`` share ``lambda_g``
    _PRIORS = {
        "S_c": ("lambda_g", "use_sc"),
        "S_p": ("lambda_g", "use_sp"),
        "S_m": ("lambda_m", "use_sm"),
        "S_l": ("lambda_l", "use_sl"),
        "S_s": ("lambda_s", None),
    }
    _STAGE = "stage1"
