"""Parameter files: the flat JSON form, its version and the replay of older files."""

import json
from pathlib import Path

import pytest

import torchiid
from torchiid.core.exceptions import ParameterError
from torchiid.params import ADDED_SINCE, Parameters
from torchiid.params.files import version_key

DATA = Path(__file__).parent / "data"


def test_json_roundtrip_flat_with_the_version(tmp_path):
    p = Parameters.preset("default").replace(iterations=3, gamma_l=7.5, luminance_weight=None)
    path = tmp_path / "p.json"
    text = p.to_json(path)
    assert path.read_text() == text
    data = json.loads(text)
    assert next(iter(data)) == "torchiid_version"  # first, where a reader looks
    assert data["torchiid_version"] == torchiid.__version__
    assert {k: v for k, v in data.items() if k != "torchiid_version"} == p.to_dict()
    assert Parameters.from_json(path) == p
    assert Parameters.from_dict(data) == p
    assert not list(tmp_path.glob(".*.tmp"))  # written atomically


def test_unknown_keys_and_bad_files_are_named(tmp_path):
    path = tmp_path / "p.json"
    path.write_text(json.dumps({"iterations": 2, "lamda_g": 1.0}))
    with pytest.raises(ParameterError, match="p.json: Invalid parameter: lamda_g"):
        Parameters.from_json(path)
    with pytest.raises(ParameterError, match="no such parameter file"):
        Parameters.from_json(tmp_path / "none.json")
    path.write_text("{not json")
    with pytest.raises(ParameterError, match="not a readable JSON"):
        Parameters.from_json(path)
    path.write_text('{"lambda_l": NaN}')
    with pytest.raises(ParameterError, match="not a readable JSON"):
        Parameters.from_json(path)
    path.write_text('{"iterations": 0}')
    with pytest.raises(ParameterError, match="p.json: parameter iterations must be > 0"):
        Parameters.from_json(path)
    for bad in ("one", 12, "v"):
        path.write_text(json.dumps({"torchiid_version": bad}))
        with pytest.raises(ParameterError, match="torchiid_version must be a version"):
            Parameters.from_json(path)
    with pytest.raises(ParameterError, match="must be a JSON object"):
        Parameters.from_dict([("iterations", 2)])


def test_partial_json_keeps_base(tmp_path):
    path = tmp_path / "p.json"
    path.write_text('{"iterations": 2}')
    p = Parameters.from_json(path, base=Parameters.preset("paper").replace(theta=3.0))
    assert p.iterations == 2 and p.reflectance.theta == 3.0
    assert p == Parameters.preset("paper").replace(theta=3.0, iterations=2)


@pytest.mark.parametrize("preset", ["default", "converged"])
def test_a_file_written_before_the_groups_loads_unchanged(preset, caplog):
    # complete records written by the flat Parameters (no version): every value as written,
    # and the parameters added since (t_x, t_x_sigma, coarse_scale, t_xc) at the values that
    # version ran, with a warning
    path = DATA / f"before-groups-{preset}-params.json"
    expected = Parameters.preset(preset).replace(t_x=0.0, t_x_sigma=3.0, coarse_scale=1.0, t_xc=0.0)
    if preset == "converged":
        expected = expected.replace(max_side=300)
    else:  # the values the default had when the file was written
        expected = expected.replace(lambda_m=0.01, lambda_s=0.01, dark_level=0.002, clip_level=0.99)
    with caplog.at_level("WARNING", logger="torchiid.params"):
        assert Parameters.from_json(path) == expected
        assert Parameters.from_json(path, base=Parameters.preset("texture")) == expected
    assert caplog.text.count("it names every parameter but coarse_scale, t_x") == 2
    assert json.loads(path.read_text()) == {
        k: v
        for k, v in expected.to_dict().items()
        if k not in ("t_x", "t_x_sigma", "coarse_scale", "t_xc")
    }


def test_versions_compare_as_numbers():
    assert version_key("0.10.0") > version_key("0.9.0") > version_key("0.9")
    assert version_key("1.0.0rc1") == (1, 0, 0)
    assert list(ADDED_SINCE) == sorted(ADDED_SINCE, key=version_key)


def test_a_versioned_file_replays_what_its_version_ran(tmp_path, caplog):
    # a 0.9.0 file of a few values: what came after 0.9.0 takes the values 0.9.0 ran; the
    # rest (older parameters it leaves out) keeps the base's
    base = Parameters.preset("converged")
    path = tmp_path / "p.json"
    path.write_text(json.dumps({"torchiid_version": "0.9.0", "iterations": 3, "t_i": 1.5}))
    with caplog.at_level("WARNING", logger="torchiid.params"):
        p = Parameters.from_json(path, base=base)
    later = {
        k: v for version, added in ADDED_SINCE.items() if version_key(version) > (0, 9, 0)
        for k, v in added.items()
    }  # fmt: skip
    assert set(later) == {
        "lambda_s", "t_e", "t_d", "t_h", "bregman_gap_tol", "bregman_theta_floor", "base_mix",
        "t_x", "t_x_sigma", "coarse_scale", "t_xc",
    }  # fmt: skip
    assert p == base.replace(iterations=3, t_i=1.5, **later)
    assert (p.shading.base_mix, p.shading.lambda_s, p.reflectance.bregman_gap_tol) == (1.0, 0, 0)
    assert p.reflectance.bregman_warm_state  # added in 0.9.0: the base's
    assert caplog.text.count("earlier torchiid") == 1 and "torchiid 0.9.0" in caplog.text
    assert "base_mix 1.0" in caplog.text
    # a value the file names is its own, whatever its version
    path.write_text(json.dumps({"torchiid_version": "0.9.0", "base_mix": 0.25}))
    assert Parameters.from_json(path, base=base).shading.base_mix == 0.25
    # "0.10.0" comes after "0.9.0" (as strings it would not): t_e is the file's base's
    path.write_text(json.dumps({"torchiid_version": "0.10.0"}))
    assert Parameters.from_json(path, base=base) == base.replace(
        bregman_gap_tol=0.0, bregman_theta_floor=1.0, base_mix=1.0, t_x_sigma=3.0, t_xc=0.0
    )
    # a file of this version: nothing to replay, no warning
    caplog.clear()
    path.write_text(base.replace(iterations=2).to_json())
    with caplog.at_level("WARNING", logger="torchiid.params"):
        assert Parameters.from_json(path) == base.replace(iterations=2)
    assert caplog.text == ""


#: the parameters before the first entry of ADDED_SINCE: a file naming all of them (and no
#: version) is a complete record of the oldest version
OLDEST = {
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
    added = {k: v for entries in ADDED_SINCE.values() for k, v in entries.items()}
    names = set(Parameters().to_dict())
    # a parameter added without an entry would make every later complete file look partial
    assert names == OLDEST | added.keys()
    assert not OLDEST & added.keys()
    assert sum(map(len, ADDED_SINCE.values())) == len(added)  # each added once
    # the recorded values are valid, and each is the one that switches its feature off
    before = Parameters(**added)
    assert before.shading.base_mix == 1.0 and before.shading.t_e == 0.0
    assert before.shading.lambda_s == 0.0 and not before.reflectance.bregman_warm_state


def test_a_complete_file_without_a_version_replays_what_it_ran(tmp_path, caplog):
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
    assert p.shading.base_mix == 1.0
    assert (p.reflectance.bregman_gap_tol, p.reflectance.bregman_theta_floor) == (0.0, 1.0)
    assert p.replace(base_mix=0.75, bregman_gap_tol=0.005, bregman_theta_floor=0.25) == base
    assert "earlier torchiid" in caplog.text and "base_mix 1.0" in caplog.text
    # from_dict reads the same record the same way
    assert Parameters.from_dict(record, base=base) == p
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


def test_a_texture_file_of_1_0_0_replays_its_3_px_removal(tmp_path):
    # 1.0.0 took the texture out of S_l's targets with a 3-px fit; its files keep it
    path = tmp_path / "p.json"
    old = Parameters.preset("texture").replace(t_x=0.05).to_dict()
    del old["t_x_sigma"]
    path.write_text(json.dumps({**old, "torchiid_version": "1.0.0"}))
    p = Parameters.from_json(path)
    assert (p.shading.t_x, p.shading.t_x_sigma) == (0.05, 3.0)
    assert Parameters.preset("texture").shading.t_x_sigma == 5.0
