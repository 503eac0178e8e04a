"""The 0.x configuration objects of the stages: deprecated, and still giving the same answers."""

import warnings

import pytest
import torch

import torchiid.stages as stages
import torchiid.stages.config as config
from torchiid.core.exceptions import ParameterError
from torchiid.params import ReflectanceParameters, ShadingParameters
from torchiid.stages import (
    ReflectanceProblem,
    ShadingProblem,
    TemporalPrior,
    build_reflectance_terms,
    build_shading_system,
    solve_reflectance,
    solve_shading,
)
from torchiid.stages.reflectance import temporal_term
from torchiid.synthetic import mondrian


def _old(name):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return getattr(stages, name)


@pytest.mark.parametrize(
    "name", ["ShadingWeights", "ShadingOptions", "ReflectanceWeights", "ReflectanceOptions"]
)
def test_reading_an_old_name_warns_and_names_its_replacement(name):
    group = "ShadingParameters" if name.startswith("Shading") else "ReflectanceParameters"
    for module in (stages, config):
        with pytest.warns(DeprecationWarning, match=f"{name} is deprecated; use .*{group}"):
            cls = getattr(module, name)
        assert cls is _old(name)
    with pytest.raises(AttributeError, match="no attribute 'ShadingOption'"):
        _ = stages.ShadingOption


def test_old_weights_keep_their_schedule_and_checks():
    weights = _old("ShadingWeights")(lambda_c=0.02, lambda_p=0.03, lambda_s=0.01)
    nxt = weights.step(1.2)
    assert (nxt.lambda_c, nxt.lambda_p, nxt.lambda_l, nxt.lambda_s) == (
        0.02 * 1.2, 0.03 * 1.2, 2.0 / 1.2, 0.01 / 1.2,
    )  # fmt: skip
    r = _old("ReflectanceWeights")().step(1.2)
    assert (r.gamma_l, r.gamma_m, r.gamma_g, r.gamma_a) == (20 / 1.2, 20 * 1.2, 2 * 1.2, 1.2)
    with pytest.raises(ParameterError, match="must be >= 0"):
        _old("ShadingWeights")(lambda_l=float("nan"))
    with pytest.raises(ParameterError, match="tau"):
        _old("ReflectanceWeights")().step(0.0)
    with pytest.raises(ParameterError, match="window must be odd"):
        _old("ReflectanceOptions")(window=4)


def test_the_old_shading_calls_warn_and_solve_the_same_system():
    syn = mondrian(24, 24, seed=2, dtype=torch.float64)
    problem = ShadingProblem(syn.image)
    # lambda_c and lambda_p apart: a weight pair the groups write as lambda_g and switches
    old_w = _old("ShadingWeights")(lambda_c=0.0, lambda_p=0.05, lambda_m=0.0, lambda_s=0.01)
    old_o = _old("ShadingOptions")(tol=1e-9, max_iter=500, levels=2, t_e=0.015)
    new = ShadingParameters(
        lambda_g=0.05, use_sc=False, lambda_m=0.0, lambda_s=0.01, t_e=0.015, dark_level=0.0,
        clip_level=0.0, base_mix=1.0, cg_tol=1e-9, cg_max_iter=500, warm_cg_max_iter=0,
        coarse_levels=2,
    )  # fmt: skip
    weights = {"lambda_g": 0.05, "use_sc": False, "lambda_m": 0.0, "lambda_s": 0.01}
    assert old_o.to_parameters().replace(**weights) == new
    with pytest.warns(DeprecationWarning, match="solve_shading\\(problem, params.shading\\)"):
        old = solve_shading(problem, old_w, old_o)
    assert torch.equal(old.log_shading, solve_shading(problem, new).log_shading)
    with pytest.warns(DeprecationWarning, match="build_shading_system"):
        system = build_shading_system(problem, old_w, old_o)
    assert {k: w for k, (w, _) in system.terms.items()} == {"S_p": 0.05, "S_l": 2.0, "S_s": 0.01}
    with pytest.raises(ParameterError, match="takes a torchiid.params.ShadingParameters"):
        solve_shading(problem, old_w)


def test_the_old_reflectance_calls_warn_and_solve_the_same_problem():
    s = mondrian(20, 24, patches=6, seed=3)
    problem = ReflectanceProblem(s.reflectance, s.image, segments=s.labels)
    old_w = _old("ReflectanceWeights")(gamma_m=0.0, gamma_a=1.5)
    old_o = _old("ReflectanceOptions")(window=5, max_outer=2, merge_stencil_terms=False)
    new = ReflectanceParameters(
        gamma_m=0.0, gamma_a=1.5, window=5, bregman_iter=2, bregman_cg_iter=5
    )
    with pytest.warns(DeprecationWarning, match="solve_reflectance"):
        old = solve_reflectance(problem, old_w, old_o)
    ref = solve_reflectance(problem, new, merge=False)
    assert torch.equal(old.reflectance, ref.reflectance)
    assert torch.equal(old.solver.objective, ref.solver.objective)  # tracked, as before
    with pytest.warns(DeprecationWarning, match="build_reflectance_terms"):
        built = build_reflectance_terms(problem, old_w, old_o)
    assert tuple(built.terms) == ("A", "C")
    prior = TemporalPrior(s.reflectance, torch.ones(1, 1, 20, 24), weight=2.0)
    with pytest.warns(DeprecationWarning, match="temporal_term"):
        gamma, _ = temporal_term(prior, s.reflectance, old_w, old_o)
    assert gamma == temporal_term(prior, s.reflectance, new)[0] == 2.0 * 1.5 * 255


def test_a_cache_in_the_options_place_is_the_cache():
    from torchiid.params.legacy import cache_in_options
    from torchiid.stages import ShadingSystemCache

    cache, options = ShadingSystemCache(), _old("ShadingOptions")()
    assert cache_in_options(cache, None, ShadingSystemCache) == (None, cache)
    assert cache_in_options(options, cache, ShadingSystemCache) == (options, cache)
    assert cache_in_options(None, None, ShadingSystemCache) == (None, None)
    problem = ShadingProblem(mondrian(16, 16, seed=1).image)
    group = ShadingParameters(lambda_m=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the new form does not warn
        build_shading_system(problem, group, cache)
        again = build_shading_system(problem, group, cache)
    assert "S_l" in again.terms and cache.hits > 0  # reused: the third argument is the cache


def test_old_weights_and_options_convert_to_the_groups_and_back():
    shading_weights, reflectance_weights = _old("ShadingWeights"), _old("ReflectanceWeights")
    assert shading_weights().as_dict() == {
        "S_c": 0.02, "S_p": 0.02, "S_m": 0.02, "S_l": 2.0, "S_s": 0.0,
    }  # fmt: skip
    assert shading_weights(0.0, 0.0, 0.0, 0.0, 0.1).active
    assert not reflectance_weights(0.0, 0.0, 0.0, 1.0).active  # the data term is no prior
    assert reflectance_weights(gamma_g=0.0).as_dict() == {"A": 20.0, "B": 20.0, "C": 0.0}
    options = _old("ShadingOptions")(levels=2, tol=1e-6, seed=3, warn=False)
    group = options.to_parameters()
    assert (group.coarse_levels, group.cg_tol) == (2, 1e-6)
    assert type(options).from_parameters(group, 3, False) == options
    assert options.replace(levels=4).to_parameters() == group.replace(coarse_levels=4)
    r_options = _old("ReflectanceOptions")(eps=1e-3, max_outer=4, merge_stencil_terms=False)
    r_group = r_options.to_parameters()
    assert (r_group.shading_floor, r_group.bregman_iter) == (1e-3, 4)
    back = type(r_options).from_parameters(r_group, track_objective=True)
    assert back == r_options.replace(merge_stencil_terms=True)
    with pytest.raises(ParameterError, match="coarse_levels"):
        options.replace(levels=0)
