import json

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.params import PRESETS, VARIANTS, Parameters


def test_paper_preset_has_the_papers_values():
    p = Parameters.preset("paper")
    assert (p.lambda_g, p.lambda_m, p.lambda_l, p.lambda_s) == (0.02, 0.02, 2.0, 0.0)
    assert (p.gamma_g, p.gamma_m, p.gamma_l, p.theta, p.tau) == (2.0, 20.0, 20.0, 40.0, 1.2)
    assert (p.t_c, p.t_m, p.t_b, p.t, p.iterations) == (1e-4, 0.05, 0.05, 0.05, 5)
    assert (p.t_i, p.t_e, p.t_d, p.t_h) == (0.0, 0.0, 0.0, 0.0)
    assert (p.patch_size, p.patch_stride, p.lle_k) == (60, 30, 10)


def test_print_preset_differs_from_default_only_in_t_h():
    default, printed = Parameters().to_dict(), Parameters.preset("print").to_dict()
    assert {k for k in default if default[k] != printed[k]} == {"t_h"}
    assert printed["t_h"] == 0.5 and Parameters.preset("converged").t_h == 0.0
    assert all(Parameters.preset(n).t_d == 0.0 for n in ("default", "print", "converged"))


def test_default_preset_differs_from_paper_only_where_tuned():
    paper, default = Parameters.preset("paper").to_dict(), Parameters.preset("default").to_dict()
    assert {k for k in paper if paper[k] != default[k]} == {
        "cg_max_iter",
        "warm_cg_max_iter",
        "bregman_iter",
        "bregman_cg_iter",
        "lambda_m",  # re-tuned with S_s
        "lambda_s",  # S_s is not one of the paper's priors
        "t_e",  # nor is S_l's cut beside colour edges
        "base_mix",  # the matting base of later alternations mixes in the image
    }
    # the no-argument object is what decompose() does by default
    assert Parameters.preset("default") == Parameters()


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
        ({"luminance_weight": -1.0}, "luminance_weight must be a number >= 0 or null"),
        ({"luminance_weight": "high"}, "luminance_weight must be a number >= 0 or null"),
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
    # a variant sets every switch: v4 then v7 is v7, not v4
    assert p.variant("v4").variant("v7") == p.variant("v7") == p
    assert p.variant("baseline2").variant("v1") == p.variant("v1")
    assert not p.variant("baseline1").stage2 and not p.variant("baseline2").stage1
    assert set(VARIANTS) >= {f"v{i}" for i in range(1, 8)} and "paper" in PRESETS


def test_stage_configuration_carries_switches_and_schedule():
    p = Parameters()
    sw, rw = p.shading_weights(), p.reflectance_weights()
    assert (sw.lambda_c, sw.lambda_p, sw.lambda_m, sw.lambda_l) == (0.02, 0.02, 0.01, 2.0)
    assert sw.lambda_s == 0.01
    assert (rw.gamma_l, rw.gamma_m, rw.gamma_g, rw.gamma_a) == (20.0, 20.0, 2.0, 1.0)
    # switches are zero weights
    v1 = p.variant("v1").shading_weights()
    assert (v1.lambda_c, v1.lambda_p, v1.lambda_m) == (0, 0, 0) and v1.lambda_l == 2.0
    assert not p.variant("baseline2").shading_weights().active
    assert not p.variant("baseline1").reflectance_weights().active
    v4 = p.variant("v4").reflectance_weights()
    assert v4.gamma_l == 20.0 and v4.gamma_m == 0 and v4.gamma_g == 0
    # the §3.4 schedule: global, mid-level and data x tau, local / tau, per alternation
    sw3, rw3 = p.shading_weights(3), p.reflectance_weights(3)
    assert sw3.lambda_c == pytest.approx(0.02 * 1.44) and sw3.lambda_l == pytest.approx(2 / 1.44)
    assert sw3.lambda_s == pytest.approx(0.01 / 1.44)  # S_s is local, like S_l
    assert rw3.gamma_l == pytest.approx(20 / 1.44) and rw3.gamma_a == pytest.approx(1.44)
    assert sw.step(1.2).step(1.2) == sw3
    # every solver knob comes from Parameters
    so, ro = p.replace(anchor=1e-6, coarse_levels=2).shading_options(), p.reflectance_options()
    assert (so.anchor, so.levels, so.max_iter, so.warm_max_iter) == (1e-6, 2, 100, 30)
    assert (ro.window, ro.value_scale, ro.max_outer, ro.cg_max_iter) == (11, 255.0, 2, 3)
    with pytest.raises(ParameterError, match="window must be odd"):
        Parameters(window=10)


#: the parameters at the architecture step (cd5b0ce), from which on a parameter file names
#: every parameter but those added since (ADDED_SINCE)
ARCHITECTURE_STEP = {
    "albedo_quantile", "anchor", "base_sigma", "bregman_cg_iter", "bregman_cg_tol",
    "bregman_iter", "bregman_tol", "cg_max_iter", "cg_tol", "clip_level", "coarse_levels",
    "colour_weights", "dark_eps", "dark_level", "feature_backend", "feature_mode", "gamma_a",
    "gamma_g", "gamma_l", "gamma_m", "guide_eps", "guide_radius", "iterations", "lambda_g",
    "lambda_l", "lambda_m", "lle_features", "lle_k", "lle_neighbours", "lle_reg", "matting_eps",
    "max_side", "patch_size", "patch_stride", "proposal_pca_dim", "seed", "segment_scale",
    "shading_floor", "stage1", "stage2", "t", "t_b", "t_c", "t_g", "t_m", "tau", "theta",
    "use_rg", "use_rl", "use_rm", "use_sc", "use_sl", "use_sm", "use_sp", "value_scale",
    "view_quantile", "warm_cg_max_iter", "window",
}  # fmt: skip


def test_every_new_parameter_records_what_ran_before_it():
    from torchiid.params import ADDED_SINCE

    names = set(Parameters().to_dict())
    # a parameter added without an entry would make every later complete file look partial
    assert names == ARCHITECTURE_STEP | ADDED_SINCE.keys()
    assert not ARCHITECTURE_STEP & ADDED_SINCE.keys()
    # the recorded values are valid, and each is the one that switches its feature off
    before = Parameters(**ADDED_SINCE)
    assert before.shading_options().base_mix == 1.0 and before.t_e == 0.0


def test_a_complete_file_from_an_earlier_version_replays_what_it_ran(tmp_path, caplog):
    # a converged-preset file written before base_mix and the duality gap existed: it names
    # every other parameter (values as written), so the missing ones take what ran then, not
    # the preset's (base_mix 0.75, gap 0.5%)
    record = Parameters.preset("converged").to_dict()
    for key in ("base_mix", "bregman_gap_tol", "bregman_theta_floor"):
        del record[key]
    path = tmp_path / "old-params.json"
    path.write_text(json.dumps(record))
    base = Parameters.preset("converged")
    with caplog.at_level("WARNING", logger="torchiid.params"):
        p = Parameters.from_json(path, base=base)
    assert (p.base_mix, p.bregman_gap_tol, p.bregman_theta_floor) == (1.0, 0.0, 1.0)
    assert p.replace(base_mix=0.75, bregman_gap_tol=0.005, bregman_theta_floor=0.25) == base
    assert "earlier torchiid" in caplog.text and "base_mix 1.0" in caplog.text
    # a file that also leaves out an older parameter is a partial one: the base fills in
    del record["tau"]
    path.write_text(json.dumps(record))
    caplog.clear()
    with caplog.at_level("WARNING", logger="torchiid.params"):
        p = Parameters.from_json(path, base=base)
    assert p == base and caplog.text == ""
    # a complete file of today, and a file of a few overrides, are read as they are
    path.write_text(Parameters.preset("converged").to_json())
    with caplog.at_level("WARNING", logger="torchiid.params"):
        assert Parameters.from_json(path, base=Parameters()) == base
        path.write_text(json.dumps({"lambda_l": 0.5}))
        assert Parameters.from_json(path, base=base) == base.replace(lambda_l=0.5)
    assert caplog.text == ""
