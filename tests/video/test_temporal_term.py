import pytest
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.eval.lmse import mit_lmse
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.solvers.split_bregman import SplitBregmanOptions, split_bregman
from torchiid.stages import ReflectanceProblem, TemporalPrior, solve_reflectance
from torchiid.stages.reflectance import TemporalAnchorTerm, TemporalL1Term
from torchiid.synthetic import mondrian

S, GA, THETA = 255.0, 1.0, 40.0 * 255.0

FAST = Parameters().replace(iterations=2, use_sc=False, use_sm=False, use_rm=False)


def data(seed=0):
    g = torch.Generator().manual_seed(seed)
    rho = torch.rand(1, 3, 8, 8, generator=g)
    target = torch.rand(1, 3, 8, 8, generator=g)
    conf = (torch.rand(1, 1, 8, 8, generator=g) > 0.3).float()
    return rho, target, conf


def test_anchor_term_is_the_exact_weighted_average():
    rho, target, conf = data()
    gamma = 4.0 * GA * S
    term = TemporalAnchorTerm(target, conf, 2 * gamma / THETA)
    o = SplitBregmanOptions(theta=THETA, max_outer=2, cg_max_iter=50, cg_tol=1e-10, tol=0.0)
    res = split_bregman(rho, [term], [gamma], gamma_a=GA * S, options=o)
    expected = (GA * S * rho + gamma * conf * target) / (GA * S + gamma * conf)
    assert torch.allclose(res.z, expected, atol=1e-5)


def test_l1_term_converges_to_its_proximal_solution():
    rho, target, conf = data(1)
    gamma = 0.2 * GA * S
    term = TemporalL1Term(target, conf)
    # (a smaller penalty than the pipeline's converges in fewer Bregman iterations)
    o = SplitBregmanOptions(theta=4 * S, max_outer=40, cg_max_iter=20, cg_tol=1e-10, tol=1e-9)
    res = split_bregman(rho, [term], [gamma], gamma_a=GA * S, options=o)
    # 1-D prox of gamma*c*|z - T| + GA*S*(z - rho)^2: snap to T within gamma*c / (2*GA*S)
    d = rho - target
    thr = gamma * conf / (2 * GA * S)
    expected = torch.where(d.abs() <= thr, target, rho - thr * d.sign())
    assert torch.allclose(res.z, expected, atol=1e-4)


def problem_with(temporal):
    img = mondrian(32, 32, seed=3).image
    return ReflectanceProblem(rho=img, image=img, temporal=temporal)


def test_zero_weight_or_no_trusted_pixel_changes_nothing():
    p = FAST
    o = p.reflectance
    base = solve_reflectance(problem_with(None), o, track_objective=False).reflectance
    img = problem_with(None).image
    for prior in (
        TemporalPrior(img * 0.5, torch.ones(1, 1, 32, 32), weight=0.0),
        TemporalPrior(img * 0.5, torch.zeros(1, 1, 32, 32), weight=4.0),
    ):
        out = solve_reflectance(problem_with(prior), o, track_objective=False)
        assert torch.equal(out.reflectance, base)


@pytest.mark.parametrize("norm, weight", [("l2", 16.0), ("l1", 2.0)])
def test_temporal_term_pulls_the_reflectance_toward_the_target(norm, weight):
    syn = mondrian(64, 64, seed=5)
    plain = decompose(syn.image, FAST)
    # the target's scale does not matter (fitted to rho)
    conf = torch.ones(1, 1, 64, 64)
    prior = TemporalPrior(3.0 * syn.reflectance, conf, weight=weight, norm=norm)
    pulled = decompose(syn.image, FAST, temporal=prior)
    lm = [float(mit_lmse(syn.reflectance, syn.shading, d.reflectance, d.shading))
          for d in (plain, pulled)]  # fmt: skip
    assert lm[1] < 0.6 * lm[0], lm
    # the target's scale (3x) is not copied: the reflectance stays an albedo
    assert float(pulled.reflectance.max()) <= 1


def test_temporal_prior_checks():
    img = mondrian(64, 64).image
    with pytest.raises(ParameterError):
        TemporalPrior(img, torch.ones(1, 1, 64, 64), norm="l3")
    with pytest.raises(ParameterError):
        TemporalPrior(img, torch.ones(1, 1, 64, 64), weight=-1)
    with pytest.raises(ShapeError, match="temporal target"):
        decompose(img, FAST, temporal=TemporalPrior(img[..., :40], torch.ones(1, 1, 64, 64)))
    with pytest.raises(ShapeError, match="TemporalPrior"):
        decompose(img, FAST, temporal=(img, img))


def test_schedule_start_runs_the_last_alternations():
    img = mondrian(64, 64).image
    p = FAST.replace(iterations=3)
    full = decompose(img, p)
    assert torch.equal(decompose(img, p, schedule_start=1).reflectance, full.reflectance)
    calls = []
    last = decompose(img, p, schedule_start=3, progress=lambda *a: calls.append(a))
    assert [r.alternation for r in last.solves] == [3, 3]
    # progress counts the alternations run, so a bar over its total ends full
    assert calls == [("features", 0, 1), ("iteration", 1, 1)]
    with pytest.raises(ParameterError, match="schedule_start"):
        decompose(img, p, schedule_start=4)


def test_features_come_back_for_reuse():
    img = mondrian(64, 64).image
    out = decompose(img, FAST, return_features=True)
    assert out.features is not None and decompose(img, FAST).features is None
    again = decompose(img, FAST, features=out.features)
    assert torch.equal(again.reflectance, out.reflectance)
