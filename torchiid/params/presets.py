"""Named parameter sets and the paper's ablation variants, in the flat form of a parameter file."""

from typing import Any

__all__ = ["PRESETS", "VARIANTS", "ALL_ON"]

#: Named parameter sets: name -> the flat parameters that differ from ``Parameters()``.
#: The values' evidence (MIT-Berkeley scores, times) is in the documentation's Method page.
PRESETS: dict[str, dict[str, Any]] = {
    # the paper's energy with two additions that hold in cross-validation (S_l's cut beside
    # colour edges, a mixed matting base) and S_l's targets without the fine texture that
    # changes colour, early-stopped solvers and the alternations before the last at half the
    # working resolution (= Parameters())
    "default": {},
    # printed matter (documents, labels, packaging, posters): S_l does not tie the pixels of
    # thin strokes either, so black text on white paper stays in the reflectance
    "print": {"t_h": 0.5, "t_x": 0.0},
    # densely textured surfaces (tiles, wood grain, patterned fabric, fur): S_l takes its
    # targets from the image without all of its fine texture, also where it keeps its colour
    # (the default only where it changes colour), so the texture stays in the reflectance
    "texture": {"t_xc": 0.0},
    # the paper's energy with the solvers at their most thorough
    "paper": {
        "base_mix": 1.0,
        "lambda_m": 0.02,
        "lambda_s": 0.0,
        "t_e": 0.0,
        "t_x": 0.0,
        "cg_max_iter": 300,
        "warm_cg_max_iter": 0,
        "bregman_iter": 4,
        "bregman_cg_iter": 5,
        "coarse_scale": 1.0,
    },
    # every solve to its tolerance (the caps are safety caps: a ConvergenceWarning if hit):
    # multigrid PCG to 1e-4, Split-Bregman to a duality gap of 0.5% with residual balancing
    # and a warm Bregman state; the energy re-tuned for solves that reach their minimum
    "converged": {
        "converge": True,
        "coarse_scale": 1.0,
        "shading_preconditioner": "multigrid",
        "cg_max_iter": 3000,
        "warm_cg_max_iter": 0,
        "theta": 2.5,  # only the splitting penalty: the minimiser does not depend on it
        "bregman_iter": 400,
        "bregman_cg_iter": 5,
        "bregman_tol": 5e-5,  # for terms that cannot measure the gap (video's temporal term)
        "bregman_gap_tol": 0.005,
        "bregman_theta_floor": 0.25,
        "bregman_cg_tol": 1e-6,
        "bregman_warm_state": True,
        "tau": 1.1,
        "gamma_l": 10.0,
        "gamma_m": 10.0,
        "gamma_g": 1.0,
        "t_i": 1.5,
        "base_mix": 0.75,
        "t_e": 0.0075,
        "matting_eps": 3e-4,
        "lambda_m": 0.005,
        "lambda_s": 0.003,
        "t_x": 0.0,
    },
}

#: every ablation switch on (a variant sets them all)
ALL_ON: dict[str, Any] = {
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

#: The paper's ablation variants (Table 3) and baselines (§5): name -> switches turned off.
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
