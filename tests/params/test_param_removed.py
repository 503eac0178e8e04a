"""Parameters' flat attribute reads and stage builders are gone; the flat form stays."""

import pytest

from torchiid.params import Parameters
from torchiid.params.parameters import FLAT_NAMES


def test_a_flat_read_names_the_group_that_holds_the_parameter():
    p = Parameters.preset("converged")
    with pytest.raises(AttributeError, match=r"no attribute 'lambda_l'; read params.shading"):
        _ = p.lambda_l
    for name, group in FLAT_NAMES.items():
        with pytest.raises(AttributeError, match=rf"; read params\.{group}\.{name}$"):
            getattr(p, name)
        assert not hasattr(p, name)
    with pytest.raises(AttributeError, match="no attribute 'lamda_l'$"):
        _ = p.lamda_l
    # the schedule's fields are Parameters' own
    assert (p.iterations, p.tau, p.seed, p.converge) == (5, 1.1, 0, True)


def test_the_flat_names_still_build_replace_and_read_files(tmp_path):
    p = Parameters(lambda_l=1.0).replace(theta=3.0)
    assert (p.shading.lambda_l, p.reflectance.theta) == (1.0, 3.0)
    assert Parameters.from_dict({"lambda_l": 1.0, "theta": 3.0}) == p
    path = tmp_path / "params.json"
    path.write_text('{"lambda_l": 1.0, "theta": 3.0}\n')
    assert Parameters.from_json(path) == p


@pytest.mark.parametrize(
    "method", ["shading_weights", "reflectance_weights", "shading_options", "reflectance_options"]
)
def test_the_stage_builders_are_gone(method):
    # their replacements: params.alternation(k), params.shading, params.reflectance
    assert not hasattr(Parameters(), method)
