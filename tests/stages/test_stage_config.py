"""The stage configuration objects: the §3.4 schedule and the named terms the stages build."""

import dataclasses

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.priors.lle import patch_rgb_features
from torchiid.priors.shading_terms import shading_stencil
from torchiid.stages.config import (
    ReflectanceOptions,
    ReflectanceProblem,
    ReflectanceWeights,
    ShadingOptions,
    ShadingProblem,
    ShadingWeights,
)
from torchiid.stages.reflectance import build_reflectance_terms
from torchiid.stages.shading import build_shading_system
from torchiid.synthetic import mondrian

TAU = 1.2  # the paper's τ


def _astuple(w):
    return tuple(getattr(w, f.name) for f in dataclasses.fields(w))


# --------------------------------------------------------------------------- §3.4 schedule
def test_shading_weights_step_follows_the_schedule():
    # §3.4: global (S_c, S_p) and mid-level (S_m) weights × τ, local (S_l, and S_s) / τ
    w = ShadingWeights(lambda_c=0.02, lambda_p=0.03, lambda_m=0.05, lambda_l=2.0, lambda_s=0.01)
    nxt = w.step(TAU)
    assert isinstance(nxt, ShadingWeights)
    assert _astuple(nxt) == (0.02 * TAU, 0.03 * TAU, 0.05 * TAU, 2.0 / TAU, 0.01 / TAU)
    assert _astuple(w) == (0.02, 0.03, 0.05, 2.0, 0.01)  # a new object, the old one unchanged
    # k steps: × τ^k and / τ^k
    k, cur = 4, w
    for _ in range(k):
        cur = cur.step(TAU)
    assert cur.lambda_c == pytest.approx(0.02 * TAU**k, rel=1e-12)
    assert cur.lambda_p == pytest.approx(0.03 * TAU**k, rel=1e-12)
    assert cur.lambda_m == pytest.approx(0.05 * TAU**k, rel=1e-12)
    assert cur.lambda_l == pytest.approx(2.0 / TAU**k, rel=1e-12)
    # a prior switched off stays off; τ = 1 changes nothing
    off = ShadingWeights(lambda_c=0.0, lambda_p=0.0).step(TAU)
    assert off.lambda_c == 0.0 and off.lambda_p == 0.0 and off.active
    assert w.step(1.0) == w


def test_reflectance_weights_step_follows_the_schedule():
    # §3.4: mid-level (γ_m), global (γ_g) and data (γ_a) weights × τ, local (γ_l) / τ
    w = ReflectanceWeights(gamma_l=20.0, gamma_m=15.0, gamma_g=2.0, gamma_a=1.0)
    nxt = w.step(TAU)
    assert isinstance(nxt, ReflectanceWeights)
    assert _astuple(nxt) == (20.0 / TAU, 15.0 * TAU, 2.0 * TAU, 1.0 * TAU)
    assert _astuple(w) == (20.0, 15.0, 2.0, 1.0)
    k, cur = 4, w
    for _ in range(k):
        cur = cur.step(TAU)
    assert cur.gamma_l == pytest.approx(20.0 / TAU**k, rel=1e-12)
    assert cur.gamma_m == pytest.approx(15.0 * TAU**k, rel=1e-12)
    assert cur.gamma_g == pytest.approx(2.0 * TAU**k, rel=1e-12)
    assert cur.gamma_a == pytest.approx(1.0 * TAU**k, rel=1e-12)
    off = ReflectanceWeights(gamma_l=0.0, gamma_m=0.0, gamma_g=0.0).step(TAU)
    assert (off.gamma_l, off.gamma_m, off.gamma_g) == (0.0, 0.0, 0.0) and not off.active
    assert w.step(1.0) == w


def test_config_validation():
    for bad in (dict(lambda_c=-1.0), dict(lambda_p=-0.1), dict(lambda_m=-1), dict(lambda_l=-2)):
        with pytest.raises(ParameterError, match="must be >= 0"):
            ShadingWeights(**bad)
    with pytest.raises(ParameterError, match="must be >= 0"):
        ShadingWeights(lambda_l=float("nan"))
    for anchor in (0.0, -1e-8):
        with pytest.raises(ParameterError, match="anchor must be > 0"):
            ShadingOptions(anchor=anchor)
    with pytest.raises(ParameterError, match="levels and max_iter"):
        ShadingOptions(levels=0)
    with pytest.raises(ParameterError, match="levels and max_iter"):
        ShadingOptions(max_iter=0)
    for bad in (dict(gamma_l=-1.0), dict(gamma_m=-1.0), dict(gamma_g=-1.0), dict(gamma_a=-1.0)):
        with pytest.raises(ParameterError, match="must be >= 0"):
            ReflectanceWeights(**bad)
    for bad in (dict(t=0.0), dict(t=-0.05), dict(t_g=-0.05)):
        with pytest.raises(ParameterError, match="deviations"):
            ReflectanceOptions(**bad)
    for window in (1, 4):
        with pytest.raises(ParameterError, match="window"):
            ReflectanceOptions(window=window)
    # replace() validates too
    with pytest.raises(ParameterError, match="anchor"):
        ShadingOptions().replace(anchor=0.0)
    with pytest.raises(ParameterError, match="warm_max_iter"):
        ShadingOptions(warm_max_iter=-5)
    with pytest.raises(ParameterError, match="tol must be > 0"):
        ShadingOptions(tol=0.0)
    with pytest.raises(ParameterError, match="lle_neighbours"):
        ShadingOptions(lle_neighbours="nearest")
    with pytest.raises(ParameterError, match="colour_weights"):
        ReflectanceOptions(colour_weights="narrow")
    with pytest.raises(ParameterError, match="luminance_weight"):
        ReflectanceOptions(luminance_weight=-1.0)
    with pytest.raises(ParameterError, match="tau"):
        ShadingWeights().step(0.0)
    with pytest.raises(ParameterError, match="tau"):
        ReflectanceWeights().step(-1.0)


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
        (ShadingWeights(), (), ("S_c", "S_p", "S_m", "S_l")),
        (ShadingWeights(lambda_c=0.0), (), ("S_p", "S_m", "S_l")),
        (ShadingWeights(lambda_p=0.0, lambda_m=0.0), (), ("S_c", "S_l")),
        (ShadingWeights(lambda_c=0.0, lambda_p=0.0), (), ("S_m", "S_l")),
        (ShadingWeights(lambda_l=0.0), (), ("S_c", "S_p", "S_m")),
        (ShadingWeights(lambda_p=0.0, lambda_m=0.0, lambda_l=0.0), (), ("S_c",)),
        # a prior without its tensors is off whatever its weight
        (ShadingWeights(), ("similarity",), ("S_c", "S_p", "S_l")),
        (ShadingWeights(), ("patch_centers", "patch_features"), ("S_p", "S_m", "S_l")),
        (
            ShadingWeights(lambda_p=0.0),
            ("patch_centers", "patch_features", "similarity"),
            ("S_l",),
        ),
    ],
)
def test_shading_system_terms_and_their_weighted_sum(weights, drop, names):
    problem = _shading_problem(batch=2).replace(**{k: None for k in drop})
    system = build_shading_system(problem, weights, ShadingOptions())
    assert tuple(system.terms) == names
    assert set(system.times) == set(names)
    for name, (lam, _) in system.terms.items():
        field = {"S_c": "lambda_c", "S_p": "lambda_p", "S_m": "lambda_m", "S_l": "lambda_l"}[name]
        assert lam == getattr(weights, field) > 0
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
    off = ShadingWeights(lambda_c=0.0, lambda_p=0.0, lambda_m=0.0, lambda_l=0.0)
    assert not off.active
    with pytest.raises(ParameterError, match="switched off"):
        build_shading_system(problem, off, ShadingOptions())


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
        (ReflectanceWeights(), True, (), ("A+B", "C")),
        (ReflectanceWeights(), False, (), ("A", "B", "C")),
        (ReflectanceWeights(), True, ("segments",), ("A+B",)),
        (ReflectanceWeights(), False, ("segments",), ("A", "B")),
        (ReflectanceWeights(gamma_g=0.0), True, (), ("A+B",)),
        (ReflectanceWeights(gamma_m=0.0), True, (), ("A", "C")),
        (ReflectanceWeights(), True, ("gpca",), ("A", "C")),
        (ReflectanceWeights(gamma_l=0.0), True, (), ("B", "C")),
        (ReflectanceWeights(gamma_l=0.0, gamma_m=0.0), True, (), ("C",)),
        (ReflectanceWeights(gamma_l=0.0, gamma_m=0.0, gamma_g=0.0), True, (), ()),
    ],
)
def test_reflectance_term_names(weights, merge, drop, names):
    s, problem = _reflectance_problem()
    problem = problem.replace(**{k: None for k in drop})
    opts = ReflectanceOptions(window=5, merge_stencil_terms=merge)
    built = build_reflectance_terms(problem, weights, opts)
    assert tuple(built.terms) == names
    gammas = {name: gamma for name, (gamma, _) in built.terms.items()}
    expected = {
        "A+B": weights.gamma_l + weights.gamma_m,
        "A": weights.gamma_l,
        "B": weights.gamma_m,
        "C": weights.gamma_g,
    }
    assert gammas == {name: expected[name] for name in names}
    n_segments = int(torch.unique(s.labels).numel())
    assert int(built.num_representatives[0]) == (n_segments if "C" in names else 0)
    assert len(built.timings) == 4


def test_merged_term_is_the_weighted_sum_of_a_and_b():
    # "A+B" at γ_l + γ_m equals γ_l·A + γ_m·B on any z (same pairs, non-negative weights)
    _, problem = _reflectance_problem()
    problem = problem.replace(rho=problem.rho.double(), gpca=problem.gpca.double())
    w = ReflectanceWeights(gamma_l=20.0, gamma_m=15.0)
    merged = build_reflectance_terms(problem, w, ReflectanceOptions(window=5))
    sep = build_reflectance_terms(
        problem, w, ReflectanceOptions(window=5, merge_stencil_terms=False)
    )
    gen = torch.Generator().manual_seed(2)
    z = torch.rand(problem.rho.shape, dtype=torch.float64, generator=gen)
    g_ab, t_ab = merged.terms["A+B"]
    (g_a, t_a), (g_b, t_b) = sep.terms["A"], sep.terms["B"]
    torch.testing.assert_close(g_ab * t_ab.l1(z), g_a * t_a.l1(z) + g_b * t_b.l1(z))
    # "C" does not depend on merging
    torch.testing.assert_close(merged.terms["C"][1].l1(z), sep.terms["C"][1].l1(z))
