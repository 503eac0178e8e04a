"""The terms each stage builds from its parameter group: names, weights and switches."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.params import ReflectanceParameters, ShadingParameters
from torchiid.priors.lle import patch_rgb_features
from torchiid.priors.shading_terms import shading_stencil
from torchiid.stages.config import ReflectanceProblem, ShadingProblem
from torchiid.stages.reflectance import build_reflectance_terms
from torchiid.stages.shading import build_shading_system
from torchiid.synthetic import mondrian

#: the paper's shading weights (lambda_g = lambda_m = 0.02, lambda_l = 2), without S_s
PAPER = ShadingParameters(lambda_m=0.02, lambda_s=0.0)
#: the paper's reflectance weights, a 5x5 window
REFL = ReflectanceParameters(window=5)


# --------------------------------------------------------------------------- shading terms
def _shading_problem(h=20, w=18, batch=1, seed=0, stride=5):
    syn = mondrian(h, w, batch=batch, seed=seed, dtype=torch.float64)
    st = shading_stencil(h, w)
    g = torch.nn.functional.one_hot(syn.labels, 16).permute(0, 3, 1, 2).double()
    sim = (g.unsqueeze(2) * st.neighbours(g)).sum(1)
    ys, xs = torch.arange(stride // 2, h, stride), torch.arange(stride // 2, w, stride)
    ctr = torch.stack(torch.meshgrid(ys, xs, indexing="ij"), -1).reshape(-1, 2)
    feats = patch_rgb_features(syn.image, ctr, patch_size=stride)
    return ShadingProblem(syn.image, patch_centers=ctr, patch_features=feats, similarity=sim)


@pytest.mark.parametrize(
    ("weights", "drop", "names"),
    [
        ({}, (), ("S_c", "S_p", "S_m", "S_l")),
        ({"use_sc": False}, (), ("S_p", "S_m", "S_l")),
        ({"use_sp": False, "lambda_m": 0.0}, (), ("S_c", "S_l")),
        ({"lambda_g": 0.0}, (), ("S_m", "S_l")),
        ({"use_sl": False}, (), ("S_c", "S_p", "S_m")),
        ({"use_sp": False, "use_sm": False, "lambda_l": 0.0}, (), ("S_c",)),
        ({"lambda_s": 0.01}, (), ("S_c", "S_p", "S_m", "S_l", "S_s")),
        ({"lambda_s": 0.01, "stage1": False}, (), ()),
        # a prior without its tensors is off whatever its weight
        ({}, ("similarity",), ("S_c", "S_p", "S_l")),
        ({}, ("patch_centers", "patch_features"), ("S_p", "S_m", "S_l")),
        ({"use_sp": False}, ("patch_centers", "patch_features", "similarity"), ("S_l",)),
    ],
)
def test_shading_system_terms_and_their_weighted_sum(weights, drop, names):
    problem = _shading_problem(batch=2).replace(**{k: None for k in drop})
    shading = PAPER.replace(**weights)
    if not names:
        with pytest.raises(ParameterError, match="switched off"):
            build_shading_system(problem, shading)
        return
    system = build_shading_system(problem, shading)
    assert tuple(system.terms) == names
    assert set(system.times) == set(names)
    for name, (lam, _) in system.terms.items():
        field = {"S_c": "lambda_g", "S_p": "lambda_g", "S_m": "lambda_m", "S_l": "lambda_l"}
        assert lam == getattr(shading, field.get(name, "lambda_s")) > 0
    b, _, h, w = problem.image.shape
    x = torch.randn(b, 1, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ref = sum(lam * term.matvec(x) for lam, term in system.terms.values())
    out = system.total.matvec(x)
    scale = float(ref.abs().max())
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-12 * scale)
    # the same for the diagonal and the right-hand side the solver uses
    torch.testing.assert_close(
        system.total.diagonal(),
        sum(lam * term.diagonal() for lam, term in system.terms.values()),
        rtol=1e-10,
        atol=1e-12 * scale,
    )
    torch.testing.assert_close(
        system.total.rhs(),
        sum(lam * term.rhs() for lam, term in system.terms.values()),
        rtol=1e-10,
        atol=1e-12 * scale,
    )


def test_shading_system_with_every_prior_off_raises():
    problem = _shading_problem()
    off = PAPER.replace(lambda_g=0.0, lambda_m=0.0, lambda_l=0.0)
    assert not off.active and not PAPER.replace(use_sl=False, lambda_g=0.0, use_sm=False).active
    with pytest.raises(ParameterError, match="switched off"):
        build_shading_system(problem, off)


# --------------------------------------------------------------------------- reflectance terms
def _reflectance_problem(h=16, w=20, seed=3):
    s = mondrian(h, w, patches=6, seed=seed)
    g = torch.Generator().manual_seed(0)
    rho = (s.reflectance + 0.03 * torch.randn(s.reflectance.shape, generator=g)).clamp(0, 1)
    codes = torch.randn(int(s.labels.max()) + 1, 4, generator=g) * 0.02
    gpca = codes[s.labels].permute(0, 3, 1, 2).contiguous()
    return s, ReflectanceProblem(rho, s.image, gpca=gpca, segments=s.labels)


@pytest.mark.parametrize(
    ("weights", "merge", "drop", "names"),
    [
        ({}, True, (), ("A+B", "C")),
        ({}, False, (), ("A", "B", "C")),
        ({}, True, ("segments",), ("A+B",)),
        ({}, False, ("segments",), ("A", "B")),
        ({"gamma_g": 0.0}, True, (), ("A+B",)),
        ({"use_rg": False}, True, (), ("A+B",)),
        ({"gamma_m": 0.0}, True, (), ("A", "C")),
        ({"use_rm": False}, True, (), ("A", "C")),
        ({}, True, ("gpca",), ("A", "C")),
        ({"gamma_l": 0.0}, True, (), ("B", "C")),
        ({"use_rl": False, "gamma_m": 0.0}, True, (), ("C",)),
        ({"gamma_l": 0.0, "gamma_m": 0.0, "gamma_g": 0.0}, True, (), ()),
        ({"stage2": False}, True, (), ()),
    ],
)
def test_reflectance_term_names(weights, merge, drop, names):
    s, problem = _reflectance_problem()
    problem = problem.replace(**{k: None for k in drop})
    group = REFL.replace(**weights)
    built = build_reflectance_terms(problem, group, merge=merge)
    assert tuple(built.terms) == names
    gammas = {name: gamma for name, (gamma, _) in built.terms.items()}
    expected = {
        "A+B": group.gamma_l + group.gamma_m,
        "A": group.gamma_l,
        "B": group.gamma_m,
        "C": group.gamma_g,
    }
    assert gammas == {name: expected[name] for name in names}
    n_segments = int(torch.unique(s.labels).numel())
    assert int(built.num_representatives[0]) == (n_segments if "C" in names else 0)
    assert len(built.timings) == 4


def test_merged_term_is_the_weighted_sum_of_a_and_b():
    # "A+B" at γ_l + γ_m equals γ_l·A + γ_m·B on any z (same pairs, non-negative weights)
    _, problem = _reflectance_problem()
    problem = problem.replace(rho=problem.rho.double(), gpca=problem.gpca.double())
    w = REFL.replace(gamma_l=20.0, gamma_m=15.0)
    merged = build_reflectance_terms(problem, w)
    sep = build_reflectance_terms(problem, w, merge=False)
    gen = torch.Generator().manual_seed(2)
    z = torch.rand(problem.rho.shape, dtype=torch.float64, generator=gen)
    g_ab, t_ab = merged.terms["A+B"]
    (g_a, t_a), (g_b, t_b) = sep.terms["A"], sep.terms["B"]
    torch.testing.assert_close(g_ab * t_ab.l1(z), g_a * t_a.l1(z) + g_b * t_b.l1(z))
    # "C" does not depend on merging
    torch.testing.assert_close(merged.terms["C"][1].l1(z), sep.terms["C"][1].l1(z))
