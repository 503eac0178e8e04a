"""The options of an evaluation run (``torchiid.eval.options``)."""

import dataclasses

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.eval import EvalOptions


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("batch_size", 0, "batch_size must be >= 1, got 0"),
        ("limit", 0, "limit must be >= 1, got 0"),
        ("delta", float("nan"), "delta must be >= 0, got nan"),
        ("delta", -0.1, "delta must be >= 0"),
        ("method", "magic", "unknown method 'magic'"),
    ],
)
def test_values_out_of_range_are_refused_when_made(field, value, message):
    with pytest.raises(ParameterError, match=message):
        EvalOptions(**{field: value})
    with pytest.raises(ParameterError, match=message):
        dataclasses.replace(EvalOptions(), **{field: value})


def test_defaults_are_a_semantic_run_that_resumes():
    o = EvalOptions()
    assert (o.method, o.batch_size, o.limit, o.resume, o.overwrite) == (
        "semantic",
        1,
        None,
        True,
        False,
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.method = "r=i"
