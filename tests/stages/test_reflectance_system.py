"""Eq. 12's priors built from the stage's parameter group: their names, weights and switches."""

import pytest
import torch

from torchiid.params import ReflectanceParameters
from torchiid.stages.config import ReflectanceProblem
from torchiid.stages.reflectance_system import build_reflectance_terms
from torchiid.synthetic import mondrian

#: the paper's reflectance weights, a 5x5 window
REFL = ReflectanceParameters(window=5)


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
