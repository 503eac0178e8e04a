import json

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.params import PRESETS, VARIANTS, Parameters


def test_paper_preset_has_the_papers_values():
    p = Parameters.preset("paper")
    assert (p.lambda_g, p.lambda_m, p.lambda_l) == (0.02, 0.02, 2.0)
    assert (p.gamma_g, p.gamma_m, p.gamma_l, p.theta, p.tau) == (2.0, 20.0, 20.0, 40.0, 1.2)
    assert (p.t_c, p.t_m, p.t_b, p.t, p.iterations) == (1e-4, 0.05, 0.05, 0.05, 5)
    assert (p.patch_size, p.patch_stride, p.lle_k) == (60, 30, 10)


def test_default_preset_differs_from_paper_only_where_tuned():
    paper, default = Parameters.preset("paper").to_dict(), Parameters.preset("default").to_dict()
    assert {k for k in paper if paper[k] != default[k]} == {
        "cg_max_iter",
        "warm_cg_max_iter",
        "bregman_iter",
        "bregman_cg_iter",
    }
    assert Parameters.preset("paper") == Parameters()


def test_json_roundtrip_and_unknown_keys(tmp_path):
    p = Parameters.preset("default").replace(iterations=3, gamma_l=7.5)
    path = tmp_path / "p.json"
    p.to_json(path)
    assert Parameters.from_json(path) == p
    path.write_text(json.dumps({"iterations": 2, "lamda_g": 1.0}))
    with pytest.raises(ParameterError, match="Invalid parameter: lamda_g"):
        Parameters.from_json(path)
    with pytest.raises(ParameterError, match="Invalid parameter: bogus"):
        p.replace(bogus=1)


def test_partial_json_keeps_base(tmp_path):
    path = tmp_path / "p.json"
    path.write_text('{"iterations": 2}')
    p = Parameters.from_json(path, base=Parameters.preset("paper").replace(theta=3.0))
    assert p.iterations == 2 and p.theta == 3.0


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"iterations": 0}, "iterations must be > 0"),
        ({"iterations": 2.5}, "iterations must be an integer"),
        ({"lambda_g": -1.0}, "lambda_g must be >= 0"),
        ({"feature_mode": "dense"}, "feature_mode must be one of shared, crop"),
        ({"use_sc": 1}, "use_sc must be true or false"),
        ({"patch_stride": 90}, "leaves pixels uncovered"),
        ({"stage1": False, "stage2": False}, "at least one of stage1"),
        ({"bregman_cg_iter": 0}, "bregman_cg_iter must be > 0"),
        ({"warm_cg_max_iter": -1}, "warm_cg_max_iter must be >= 0"),
        ({"colour_weights": "narrow"}, "colour_weights must be one of bi, wide"),
    ],
)
def test_invalid_values_are_named(changes, message):
    with pytest.raises(ParameterError, match=message):
        Parameters(**changes)


def test_bad_files_and_names(tmp_path):
    with pytest.raises(ParameterError, match="no such parameter file"):
        Parameters.from_json(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ParameterError, match="not a readable JSON"):
        Parameters.from_json(tmp_path / "bad.json")
    with pytest.raises(ParameterError, match="unknown preset 'fast'"):
        Parameters.preset("fast")
    with pytest.raises(ParameterError, match="unknown variant 'v9'"):
        Parameters().variant("v9")


def test_variants_switch_the_right_priors():
    p = Parameters()
    assert not any([p.variant("v1").use_sc, p.variant("v1").use_sp, p.variant("v1").use_sm])
    assert p.variant("v1").use_rm and p.variant("v1").use_rg
    assert p.variant("v4").use_rl and not p.variant("v4").use_rm and not p.variant("v4").use_rg
    assert p.variant("v7") == p
    assert not p.variant("baseline1").stage2 and not p.variant("baseline2").stage1
    assert set(VARIANTS) >= {f"v{i}" for i in range(1, 8)} and "paper" in PRESETS
