"""The parameter groups' fields: their documentation, valid ranges and schedule."""

import dataclasses

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.params import (
    PRESETS,
    FeatureParameters,
    OutputParameters,
    Parameters,
    ReflectanceParameters,
    ShadingParameters,
)
from torchiid.params.fields import SCHEDULE_DOWN, SCHEDULE_UP
from torchiid.priors.reflectance_terms import COLOUR_WEIGHTS

GROUPS = (FeatureParameters, ShadingParameters, ReflectanceParameters, OutputParameters)


def _leaves(cls=Parameters, path=()):
    """What a documentation generator sees: every leaf field, recursing into the groups."""
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(f.type):
            yield from _leaves(f.type, (*path, f.name))
        else:
            yield (*path, f.name), f


def test_every_leaf_documents_its_meaning_paper_value_and_range():
    leaves = list(_leaves())
    assert len(leaves) == len(Parameters().to_dict())
    for path, f in leaves:
        meta = f.metadata
        assert set(meta) <= {"doc", "paper", "valid", "why", "schedule"}, path
        assert meta["doc"] and "\n" not in meta["doc"], path
        assert "paper" in meta and isinstance(meta["valid"], str), path
        if "why" in meta:  # a short fact, not a narrative
            assert len(meta["why"]) < 160 and "\n" not in meta["why"], path
    for f in dataclasses.fields(Parameters):
        if dataclasses.is_dataclass(f.type):
            assert f.metadata["doc"]  # the groups are documented too


def test_every_tuned_value_says_why_it_differs():
    # a default that differs from the paper, or from the paper preset, is a tuned value
    paper = Parameters.preset("paper").to_dict()
    for path, f in _leaves():
        default, name = f.default, path[-1]
        tuned = (f.metadata["paper"] is not None and f.metadata["paper"] != default) or (
            paper[name] != default
        )
        if tuned:
            assert "why" in f.metadata, path


def test_the_presets_values_are_valid_and_every_default_is_in_its_range():
    for name in PRESETS:
        Parameters.preset(name)
    for cls in GROUPS:
        cls()  # the defaults pass their own checks
    assert ReflectanceParameters.__dataclass_fields__["colour_weights"].metadata["valid"] == (
        "one of " + ", ".join(COLOUR_WEIGHTS)
    )


@pytest.mark.parametrize(
    ("cls", "changes", "message"),
    [
        (ShadingParameters, {"lambda_l": -2.0}, "parameter lambda_l must be >= 0, got -2.0"),
        (ShadingParameters, {"anchor": 0.0}, "parameter anchor must be > 0, got 0.0"),
        (ShadingParameters, {"coarse_levels": 0}, "coarse_levels must be > 0"),
        (ShadingParameters, {"lle_neighbours": "nearest"}, "one of knn, random, got 'nearest'"),
        (ShadingParameters, {"t_h": float("nan")}, "t_h must be >= 0, got nan"),
        (ReflectanceParameters, {"t": 0.0}, "parameter t must be > 0, got 0.0"),
        (ReflectanceParameters, {"window": 4}, "window must be odd and >= 3"),
        (ReflectanceParameters, {"bregman_theta_floor": 0.0}, "in \\(0, 1\\]"),
        (FeatureParameters, {"patch_stride": 61}, "leaves pixels uncovered"),
        (OutputParameters, {"max_side": -1}, "max_side must be >= 0"),
    ],
)
def test_each_group_checks_its_fields(cls, changes, message):
    with pytest.raises(ParameterError, match=message):
        cls(**changes)
    with pytest.raises(ParameterError, match=message):
        cls().replace(**changes)
    with pytest.raises(ParameterError, match="Invalid parameter: lambda_q"):
        cls().replace(lambda_q=1.0)


def test_the_schedule_is_declared_next_to_each_weight():
    up = {
        (cls.__name__, f.name)
        for cls in GROUPS
        for f in dataclasses.fields(cls)
        if f.metadata.get("schedule") == SCHEDULE_UP
    }
    down = {
        (cls.__name__, f.name)
        for cls in GROUPS
        for f in dataclasses.fields(cls)
        if f.metadata.get("schedule") == SCHEDULE_DOWN
    }
    # §3.4: mid-level, global and data weights × τ, local ones ÷ τ (S_s is local)
    assert up == {
        ("ShadingParameters", "lambda_g"),
        ("ShadingParameters", "lambda_m"),
        ("ReflectanceParameters", "gamma_m"),
        ("ReflectanceParameters", "gamma_g"),
        ("ReflectanceParameters", "gamma_a"),
    }
    assert down == {
        ("ShadingParameters", "lambda_l"),
        ("ShadingParameters", "lambda_s"),
        ("ReflectanceParameters", "gamma_l"),
    }
    w = ReflectanceParameters(gamma_l=20.0, gamma_m=15.0, gamma_g=2.0, gamma_a=1.0)
    nxt = w.step(1.2)
    assert (nxt.gamma_l, nxt.gamma_m, nxt.gamma_g, nxt.gamma_a) == (20 / 1.2, 18.0, 2.4, 1.2)
    assert nxt.replace(gamma_l=20.0, gamma_m=15.0, gamma_g=2.0, gamma_a=1.0) == w
    assert w.step(1.0) == w
    off = ShadingParameters(use_sc=False, use_sp=False).step(1.2)
    assert off.weights()["S_c"] == off.weights()["S_p"] == 0.0 and off.active
