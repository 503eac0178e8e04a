"""The parameter group of Stage 2, the L1 reflectance solve (paper §3.3-3.4, Eqs. 6-13)."""

import dataclasses

from torchiid.params.fields import SCHEDULE_DOWN, SCHEDULE_UP, StageGroup, param, switch

__all__ = ["ReflectanceParameters"]


@dataclasses.dataclass(frozen=True)
class ReflectanceParameters(StageGroup):
    """Stage 2: the weights and constants of Eq. 12, their switches, the Split-Bregman solve.

    :func:`~torchiid.stages.reflectance.solve_reflectance` takes this group as it is; at
    alternation ``k`` the weights are those of :meth:`~torchiid.params.Parameters.alternation`
    (§3.4). :meth:`weights` gives each sparsity prior's weight, 0 where a switch turns it off.
    The paper's gammas and θ are for Bi et al.'s 8-bit values (``value_scale``; see
    :mod:`torchiid.stages.reflectance`).
    """

    gamma_l: float = param(
        20.0,
        "weight of the local sparsity term ‖A z‖₁",
        paper=20.0,
        valid=">= 0",
        schedule=SCHEDULE_DOWN,
    )
    gamma_m: float = param(
        20.0,
        "weight of the mid-level sparsity term ‖B z‖₁",
        paper=20.0,
        valid=">= 0",
        schedule=SCHEDULE_UP,
    )
    gamma_g: float = param(
        2.0,
        "weight of the global sparsity term ‖C z‖₁",
        paper=2.0,
        valid=">= 0",
        schedule=SCHEDULE_UP,
    )
    gamma_a: float = param(
        1.0, "weight of the data term ‖z - ρ‖²", valid=">= 0", schedule=SCHEDULE_UP
    )
    theta: float = param(40.0, "Split-Bregman penalty θ", paper=40.0, valid="> 0")
    value_scale: float = param(
        255.0,
        "intensity unit of the gammas and θ (255: the paper's values are for 8-bit values)",
        valid="> 0",
    )
    t: float = param(
        0.05, "deviation of the reflectance weights v_ij (Eq. 7)", paper=0.05, valid="> 0"
    )
    t_g: float = param(0.0, "deviation for g̊ in B's weights, Eq. 9 (0: t)", valid=">= 0")
    window: int = param(11, "side of the local window of A and B (px)", paper=11, valid="odd, >= 3")
    colour_weights: str = param(
        "bi",
        "scaling of the colour features r̄ of v_ij: 'bi' (Bi et al.'s weight function, "
        "(0.5·L/100, a/36.7, b/36.7)) or 'wide' ((0.1·L/100, a/220, b/220))",
        valid="one of bi, wide",
    )
    luminance_weight: float | None = param(
        None,
        "weight of L in r̄ (null: that of colour_weights); larger values keep neighbours that "
        "differ mainly in lightness apart",
        valid=">= 0 or null",
    )
    bregman_iter: int = param(
        2,
        "outer Split-Bregman iterations per alternation (the cap, with a tolerance)",
        valid="> 0",
        why="2 with 3 CG steps each: an early-stopped L1 solve; more iterations flatten "
        "further and score worse on MIT-Berkeley (paper preset: 4)",
    )
    bregman_cg_iter: int = param(
        3,
        "CG iterations of each Split-Bregman z step (an inexact solve the Bregman updates absorb)",
        valid="> 0",
        why="3: likewise (paper preset: 5)",
    )
    bregman_tol: float = param(
        1e-3, "relative change of z at which Split-Bregman stops", valid="> 0"
    )
    bregman_gap_tol: float = param(
        0.0,
        "relative duality gap of Eq. 12 at which Split-Bregman stops (0: stop on bregman_tol)",
        valid=">= 0",
    )
    bregman_theta_floor: float = param(
        1.0,
        "with bregman_gap_tol, residual balancing may lower θ to θ · bregman_theta_floor "
        "(1: a fixed θ)",
        valid="in (0, 1]",
    )
    bregman_cg_tol: float = param(
        1e-3, "relative residual at which each z step's CG stops", valid="> 0"
    )
    bregman_warm_state: bool = param(
        False,
        "start each alternation's Split-Bregman from the previous one's Bregman variable "
        "(same minimiser, fewer iterations)",
        valid="true or false",
    )
    shading_floor: float = param(
        1e-4,
        "smallest shading value and floor of Σ_c R_c in the gray-shading ratio (R = I / S "
        "stays finite)",
        valid="> 0",
    )
    use_rl: bool = switch("A, R_l")
    use_rm: bool = switch("B, R_m")
    use_rg: bool = switch("C, R_g")
    stage2: bool = switch("the whole stage", "off: baseline 1")

    #: the sparsity priors of :meth:`weights`; the data term's weight is ``gamma_a``
    _PRIORS = {"A": ("gamma_l", "use_rl"), "B": ("gamma_m", "use_rm"), "C": ("gamma_g", "use_rg")}
    _STAGE = "stage2"
