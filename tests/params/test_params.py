"""Parameters: presets, variants, the flat form and the §3.4 schedule."""

import dataclasses

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.params import (
    PRESETS,
    VARIANTS,
    FeatureParameters,
    OutputParameters,
    Parameters,
    ReflectanceParameters,
    ShadingParameters,
)


def test_paper_preset_has_the_papers_values():
    p = Parameters.preset("paper")
    sh, re, f = p.shading, p.reflectance, p.features
    assert (sh.lambda_g, sh.lambda_m, sh.lambda_l, sh.lambda_s) == (0.02, 0.02, 2.0, 0.0)
    assert (re.gamma_g, re.gamma_m, re.gamma_l, re.theta, p.tau) == (2.0, 20.0, 20.0, 40.0, 1.2)
    assert (sh.t_c, sh.t_m, sh.t_b, re.t, p.iterations) == (1e-4, 0.05, 0.05, 0.05, 5)
    assert (sh.t_i, sh.t_e, sh.t_d, sh.t_h) == (0.0, 0.0, 0.0, 0.0)
    assert (f.patch_size, f.patch_stride, sh.lle_k) == (60, 30, 10)


def test_print_preset_differs_from_default_only_in_t_h_and_no_texture_marks():
    default, printed = Parameters().to_dict(), Parameters.preset("print").to_dict()
    assert {k for k in default if default[k] != printed[k]} == {"t_h", "t_x"}
    assert printed["t_x"] == 0.0
    assert printed["t_h"] == 0.5 and Parameters.preset("converged").shading.t_h == 0.0
    assert all(Parameters.preset(n).shading.t_d == 0.0 for n in ("default", "print", "converged"))


def test_default_preset_differs_from_paper_only_where_tuned():
    paper, default = Parameters.preset("paper").to_dict(), Parameters.preset("default").to_dict()
    assert {k for k in paper if paper[k] != default[k]} == {
        "cg_max_iter",
        "warm_cg_max_iter",
        "bregman_iter",
        "bregman_cg_iter",
        "t_e",  # nor is S_l's cut beside colour edges
        "base_mix",  # the matting base of later alternations mixes in the image
        "t_x",  # nor are S_l's targets without the fine texture that changes colour
        "coarse_scale",  # all but the last alternation at half the size (a solver setting)
    }
    # the no-argument object is what decompose() does by default
    assert Parameters.preset("default") == Parameters()


def test_the_groups_are_the_stages_objects_and_flat_names_reach_them():
    p = Parameters(lambda_l=1.0, window=9, max_side=0, patch_size=40, iterations=2)
    assert isinstance(p.shading, ShadingParameters) and p.shading.lambda_l == 1.0
    assert isinstance(p.reflectance, ReflectanceParameters) and p.reflectance.window == 9
    assert isinstance(p.output, OutputParameters) and p.output.max_side == 0
    assert isinstance(p.features, FeatureParameters) and p.features.patch_size == 40
    assert p.iterations == 2
    # a group given whole, then a flat change on top of it
    q = Parameters(shading=ShadingParameters(lambda_l=1.0), t_c=2e-4)
    assert q.shading == ShadingParameters(lambda_l=1.0, t_c=2e-4)
    # replace by flat name or by group; every other value is kept
    r = p.replace(gamma_l=7.5, output=OutputParameters(max_side=256))
    assert r.reflectance.gamma_l == 7.5 and r.reflectance.window == 9
    assert r.output.max_side == 256 and r.shading == p.shading and r.iterations == 2
    assert p.replace() == p and hash(p.replace()) == hash(p)
    with pytest.raises(ParameterError, match="Invalid parameter: bogus"):
        p.replace(bogus=1)
    with pytest.raises(ParameterError, match="Invalid parameter: lamda_g"):
        Parameters(lamda_g=1.0)
    with pytest.raises(ParameterError, match="shading must be a ShadingParameters, got dict"):
        Parameters(shading={"lambda_l": 1.0})


def test_the_flat_form_names_every_leaf_once():
    flat = Parameters.preset("converged").to_dict()
    groups = [f.name for f in dataclasses.fields(Parameters) if dataclasses.is_dataclass(f.type)]
    assert groups == ["features", "shading", "reflectance", "output"]
    leaves = [
        g.name
        for f in dataclasses.fields(Parameters)
        for g in (dataclasses.fields(f.type) if f.name in groups else [f])
    ]
    assert len(leaves) == len(set(leaves)) == len(flat) and set(leaves) == set(flat)
    assert Parameters.from_dict(flat) == Parameters.preset("converged")
    # every preset and variant is in the flat form
    for changes in (*PRESETS.values(), *VARIANTS.values()):
        assert set(changes) <= set(flat)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"iterations": 0}, "parameter iterations must be > 0, got 0"),
        ({"iterations": 2.5}, "iterations must be an integer"),
        ({"lambda_g": -1.0}, "parameter lambda_g must be >= 0, got -1.0"),
        ({"lambda_g": float("nan")}, "lambda_g must be >= 0, got nan"),
        ({"feature_mode": "dense"}, "feature_mode must be one of shared, crop, got 'dense'"),
        ({"use_sc": 1}, "use_sc must be true or false"),
        ({"patch_stride": 90}, "leaves pixels uncovered"),
        ({"stage1": False, "stage2": False}, "at least one of stage1"),
        ({"bregman_cg_iter": 0}, "bregman_cg_iter must be > 0"),
        ({"warm_cg_max_iter": -1}, "warm_cg_max_iter must be >= 0"),
        ({"colour_weights": "narrow"}, "colour_weights must be one of bi, wide"),
        ({"luminance_weight": -1.0}, "luminance_weight must be a number >= 0 or null"),
        ({"luminance_weight": "high"}, "luminance_weight must be a number >= 0 or null"),
        ({"window": 10}, "window must be odd and >= 3, got 10"),
        ({"base_mix": 1.5}, "base_mix must be in \\[0, 1\\], got 1.5"),
        ({"view_quantile": 0.0}, "view_quantile must be in \\(0, 1\\], got 0.0"),
        ({"seed": 1.5}, "seed must be an integer"),
        ({"tau": "fast"}, "tau must be a number, got 'fast'"),
        ({"lambda_l": 1e308}, "lambda_l must be a finite number within float32's range"),
        ({"theta": float("inf")}, "theta must be a finite number within float32's range"),
        ({"luminance_weight": float("inf")}, "luminance_weight must be a finite number"),
        ({"max_side": 30}, "max_side must be 0 \\(no resizing\\) or at least patch_size \\(60\\)"),
    ],
)
def test_invalid_values_are_named(changes, message):
    with pytest.raises(ParameterError, match=message):
        Parameters(**changes)


def test_integers_are_read_as_floats_where_a_number_is_due():
    p = Parameters(lambda_l=1, theta=40, luminance_weight=1)
    assert isinstance(p.shading.lambda_l, float) and isinstance(p.reflectance.theta, float)
    assert isinstance(p.reflectance.luminance_weight, float)
    assert p == Parameters(lambda_l=1.0, theta=40.0, luminance_weight=1.0)


def test_presets_and_variants_by_name():
    with pytest.raises(ParameterError, match="unknown preset 'fast'"):
        Parameters.preset("fast")
    with pytest.raises(ParameterError, match="unknown variant 'v9'"):
        Parameters().variant("v9")


def test_variants_switch_the_right_priors():
    p = Parameters()
    v1, v4 = p.variant("v1"), p.variant("v4")
    assert not any([v1.shading.use_sc, v1.shading.use_sp, v1.shading.use_sm])
    assert v1.reflectance.use_rm and v1.reflectance.use_rg
    assert v4.reflectance.use_rl and not v4.reflectance.use_rm and not v4.reflectance.use_rg
    assert p.variant("v7") == p
    # a variant sets every switch: v4 then v7 is v7, not v4
    assert p.variant("v4").variant("v7") == p.variant("v7") == p
    assert p.variant("baseline2").variant("v1") == p.variant("v1")
    assert not p.variant("baseline1").reflectance.stage2
    assert not p.variant("baseline2").shading.stage1
    assert set(VARIANTS) >= {f"v{i}" for i in range(1, 8)} and "paper" in PRESETS


def test_stage_groups_carry_switches_and_schedule():
    p = Parameters()
    sw, rw = p.shading.weights(), p.reflectance.weights()
    assert sw == {"S_c": 0.02, "S_p": 0.02, "S_m": 0.02, "S_l": 2.0, "S_s": 0.0}
    assert rw == {"A": 20.0, "B": 20.0, "C": 2.0} and p.reflectance.gamma_a == 1.0
    # switches are zero weights, in one place
    v1 = p.variant("v1").shading.weights()
    assert (v1["S_c"], v1["S_p"], v1["S_m"]) == (0, 0, 0) and v1["S_l"] == 2.0
    assert not p.variant("baseline2").shading.active
    assert not p.variant("baseline1").reflectance.active
    v4 = p.variant("v4").reflectance.weights()
    assert v4 == {"A": 20.0, "B": 0.0, "C": 0.0}
    # the §3.4 schedule: global, mid-level and data x tau, local / tau, per alternation
    assert p.alternation(1) == (p.shading, p.reflectance)
    p = p.replace(lambda_s=0.01)  # S_s on, to see its schedule
    sh3, re3 = p.alternation(3)
    assert sh3.lambda_g == pytest.approx(0.02 * 1.44) and sh3.lambda_l == pytest.approx(2 / 1.44)
    assert sh3.lambda_m == pytest.approx(0.02 * 1.44)
    assert sh3.lambda_s == pytest.approx(0.01 / 1.44)  # S_s is local, like S_l
    assert re3.gamma_l == pytest.approx(20 / 1.44) and re3.gamma_a == pytest.approx(1.44)
    assert re3.gamma_m == pytest.approx(20 * 1.44) and re3.gamma_g == pytest.approx(2 * 1.44)
    assert p.shading.step(1.2).step(1.2) == sh3
    # everything but the weights is as configured, switches included
    assert sh3.replace(lambda_g=0.02, lambda_m=0.02, lambda_l=2.0, lambda_s=0.01) == p.shading
    assert p.variant("v1").alternation(3)[0].weights()["S_c"] == 0.0
    with pytest.raises(ParameterError, match="tau must be > 0"):
        p.shading.step(0.0)
    # every solver knob is in the stage's group
    sh = p.replace(anchor=1e-6, coarse_levels=2).shading
    assert (sh.anchor, sh.coarse_levels, sh.cg_max_iter, sh.warm_cg_max_iter) == (1e-6, 2, 100, 30)
    re = p.reflectance
    assert (re.window, re.value_scale, re.bregman_iter, re.bregman_cg_iter) == (11, 255.0, 2, 3)


def test_parameters_pickle_and_copy():
    import copy
    import pickle

    p = Parameters.preset("converged").variant("v4")
    assert pickle.loads(pickle.dumps(p)) == p
    assert copy.deepcopy(p) == p and copy.copy(p) == p


def test_numpy_numbers_are_read_as_python_numbers():
    np = pytest.importorskip("numpy")
    p = Parameters(iterations=np.int64(3), lambda_l=np.float32(2.5), max_side=np.int32(0))
    assert p == Parameters(iterations=3, lambda_l=2.5, max_side=0)
    assert type(p.iterations) is int and type(p.shading.lambda_l) is float
    with pytest.raises(ParameterError, match="iterations must be an integer"):
        Parameters(iterations=np.float64(3.0))
