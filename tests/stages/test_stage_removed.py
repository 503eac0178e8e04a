"""The stages' 0.x configuration objects and call form are gone, with errors that say so."""

import pytest
import torch

import torchiid.stages as stages
import torchiid.stages.config as config
from torchiid.core.exceptions import ParameterError
from torchiid.params import ReflectanceParameters, ShadingParameters
from torchiid.stages import (
    ReflectanceProblem,
    ShadingProblem,
    ShadingSystemCache,
    TemporalPrior,
    build_reflectance_terms,
    build_shading_system,
    solve_reflectance,
    solve_shading,
)
from torchiid.stages.config import REMOVED
from torchiid.stages.reflectance import temporal_term
from torchiid.synthetic import mondrian

OLD_NAMES = ["ShadingWeights", "ShadingOptions", "ReflectanceWeights", "ReflectanceOptions"]


@pytest.mark.parametrize("name", OLD_NAMES)
def test_reading_an_old_name_says_what_replaces_it(name):
    group = "ShadingParameters" if name.startswith("Shading") else "ReflectanceParameters"
    attribute = "shading" if name.startswith("Shading") else "reflectance"
    expected = rf"^{name} was removed in 1\.2\.0; use torchiid\.params\.{group} "
    expected += rf"\(params\.{attribute}"
    for module in (stages, config):
        with pytest.raises(ImportError, match=expected):
            getattr(module, name)
        with pytest.raises(ImportError, match=expected):
            exec(f"from {module.__name__} import {name}", {})
    assert REMOVED.keys() == set(OLD_NAMES)


def test_other_missing_names_are_plain_attribute_errors():
    with pytest.raises(AttributeError, match="module 'torchiid.stages' has no attribute 'Shad'"):
        _ = stages.Shad
    assert not hasattr(config, "ShadingOption")
    with pytest.raises(ImportError, match="cannot import name 'ShadingOption'"):
        exec("from torchiid.stages import ShadingOption", {})
    with pytest.raises(ModuleNotFoundError):
        exec("import torchiid.params.legacy", {})


def test_the_stage_calls_take_one_parameter_group():
    syn = mondrian(16, 16, seed=1, dtype=torch.float64)
    problem, group = ShadingProblem(syn.image), ShadingParameters(lambda_m=0.0)
    with pytest.raises(ParameterError, match="solve_shading takes a torchiid.params.Shading"):
        solve_shading(problem, ReflectanceParameters())
    with pytest.raises(ParameterError, match=r"build_shading_system takes .* \(params.shading\)"):
        build_shading_system(problem, object())
    # the old (problem, weights, options) form: no third positional argument
    with pytest.raises(TypeError, match="2 positional arguments but 3 were given"):
        solve_shading(problem, group, group)
    r_problem = ReflectanceProblem(syn.reflectance, syn.image)
    with pytest.raises(TypeError, match="2 positional arguments but 3 were given"):
        solve_reflectance(r_problem, ReflectanceParameters(), ReflectanceParameters())
    with pytest.raises(ParameterError, match=r"build_reflectance_terms .* \(params.reflectance\)"):
        build_reflectance_terms(r_problem, group)


def test_the_third_argument_of_a_build_is_its_cache():
    problem = ShadingProblem(mondrian(16, 16, seed=1).image)
    group, cache = ShadingParameters(lambda_m=0.0), ShadingSystemCache()
    build_shading_system(problem, group, cache)
    again = build_shading_system(problem, group, cache)
    assert "S_l" in again.terms and cache.hits > 0


def test_the_temporal_term_takes_the_mask_fourth():
    s = mondrian(20, 24, patches=6, seed=3)
    prior = TemporalPrior(s.reflectance, torch.ones(1, 1, 20, 24), weight=2.0)
    group = ReflectanceParameters(gamma_a=1.5)
    mask = torch.zeros(1, 1, 20, 24, dtype=torch.bool)
    assert temporal_term(prior, s.reflectance, group)[0] == 2.0 * 1.5 * 255
    assert temporal_term(prior, s.reflectance, group, mask) is None  # no trusted pixel
    with pytest.raises(ParameterError, match="temporal_term takes a torchiid.params.Reflectance"):
        temporal_term(prior, s.reflectance, ShadingParameters())
