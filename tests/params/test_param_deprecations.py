"""The flat attribute reads and stage builders of Parameters: deprecated, and still right."""

import pytest

from torchiid.params import Parameters
from torchiid.params.parameters import FLAT_NAMES


def test_flat_reads_warn_and_resolve_to_the_group_field():
    p = Parameters.preset("converged")
    expected = r"Parameters.lambda_l is deprecated; use params.shading.lambda_l"
    with pytest.warns(DeprecationWarning, match=expected):
        assert p.lambda_l == p.shading.lambda_l
    for name, group in FLAT_NAMES.items():
        with pytest.warns(DeprecationWarning, match=f"params.{group}.{name}"):
            assert getattr(p, name) == getattr(getattr(p, group), name)
    # the schedule's fields are Parameters' own: no warning (the suite turns warnings into
    # errors)
    assert (p.iterations, p.tau, p.seed, p.converge) == (5, 1.1, 0, True)
    with pytest.raises(AttributeError, match="no attribute 'lamda_l'"):
        _ = p.lamda_l


def test_the_stage_builders_warn_and_give_the_old_objects():
    p = Parameters().variant("v1")
    with pytest.warns(DeprecationWarning, match="shading_weights.*params.alternation"):
        sw = p.shading_weights(3)
    sh3, re3 = p.alternation(3)
    w = sh3.weights()
    assert (sw.lambda_c, sw.lambda_p, sw.lambda_m, sw.lambda_l, sw.lambda_s) == (
        w["S_c"], w["S_p"], w["S_m"], w["S_l"], w["S_s"],
    )  # fmt: skip
    with pytest.warns(DeprecationWarning, match="reflectance_weights"):
        rw = p.reflectance_weights(3)
    assert (rw.gamma_l, rw.gamma_m, rw.gamma_g, rw.gamma_a) == (
        re3.gamma_l, re3.gamma_m, re3.gamma_g, re3.gamma_a,
    )  # fmt: skip
    with pytest.warns(DeprecationWarning, match="shading_options.*params.shading"):
        so = p.shading_options()
    # the options are the group's constants and settings (its weights and switches aside)
    assert so.to_parameters() == p.shading.replace(use_sc=True, use_sp=True, use_sm=True)
    assert (so.max_iter, so.warm_max_iter, so.levels, so.seed, so.warn) == (100, 30, 3, 0, False)
    with pytest.warns(DeprecationWarning, match="reflectance_options.*params.reflectance"):
        ro = p.reflectance_options()
    assert (ro.max_outer, ro.cg_max_iter, ro.eps, ro.track_objective) == (2, 3, 1e-4, False)
    assert ro.to_parameters() == p.reflectance
