"""``tools/cv_mit.py``: its parameter lists without data, its scoring on the shared MIT data."""

import importlib.util
import re
from pathlib import Path

import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.eval import mit_lmse
from torchiid.eval.crossval import JsonlCache, reversion_test
from torchiid.model import decompose
from torchiid.params import Parameters

ROOT = Path(__file__).resolve().parents[2]
MIT_REAL = ROOT / ".." / "shared" / "data" / "mit-berkeley"


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("cv_mit", ROOT / "tools" / "cv_mit.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_revert_list_finds_the_defaults_that_differ_from_the_paper(tool):
    energy, solver = tool.revert_list("default", None)
    paper, default = Parameters.preset("paper").to_dict(), Parameters().to_dict()
    for name, value in energy.items():
        assert default[name] != value
        assert name in tool.PAPER_OFF or paper[name] == value
    assert {"t_e", "base_mix", "dark_level", "clip_level"} <= set(energy)
    assert set(solver) == {"cg_max_iter", "warm_cg_max_iter", "bregman_iter", "bregman_cg_iter"}
    assert not set(energy) & set(tool.SOLVER_FIELDS)
    # the paper preset differs from itself only by the additions it leaves on
    energy, solver = tool.revert_list("paper", None)
    assert set(energy) == set(tool.PAPER_OFF) and solver == {}


def test_revert_list_reads_given_values_and_rejects_unknown_names(tool):
    energy, solver = tool.revert_list("default", ["lambda_s=0", "cg_max_iter=300"])
    assert energy == {"lambda_s": 0} and solver == {"cg_max_iter": 300}
    with pytest.raises(ParameterError, match="Invalid parameter: lamda_s"):
        tool.revert_list("default", ["lamda_s=0"])


def test_revert_tests_and_table(tool):
    base = Parameters().replace(lambda_s=0.01)
    tests = tool.revert_tests(base, {"lambda_s": 0.0, "t_e": 0.0}, {"cg_max_iter": 300})
    assert list(tests) == ["lambda_s", "t_e", "all of the above", "cg_max_iter (cap)"]
    assert tests["all of the above"] == {"lambda_s": 0.0, "t_e": 0.0}
    names = ["a", "b", "c", "d"]

    def score(changes, sample):
        return 0.01 * (1 + names.index(sample)) + 0.001 * len(changes)

    rows = reversion_test(score, names, tests, k=2)
    text = tool.revert_table(rows, base, len(names))
    lines = text.splitlines()
    assert lines[0].startswith("| value | A's | B's | A: as given | B: changed | B − A |")
    assert lines[2].startswith("| lambda_s | 0.01 | 0.0 | 0.02500 | 0.02600 | 0.00100 |")
    assert "| 0.01, 0.015 | 0.0, 0.0 |" in lines[4]
    assert lines[5].startswith("| cg_max_iter (cap) | 100 | 300 |")
    # B is worse by 0.001 on every object: se(B − A) = 0, so only the paired rule keeps A
    assert all(line.endswith("| T T | 0.02500 | revert | revert | keep |") for line in lines[2:4])


def test_cache_keys_ignore_additions_that_are_off(tool):
    from torchiid.params import ADDED_SINCE

    default = tool.key_params(Parameters())
    assert "t_e" in default  # on in the default: part of the key
    assert "lambda_s" not in default  # added in 0.10.0, off in the default
    flat, off = Parameters().to_dict(), {k: v for a in ADDED_SINCE.values() for k, v in a.items()}
    assert not {k for k, v in off.items() if flat[k] == v} & set(default)
    assert tool.key_params(Parameters().replace(t_x=0.05))["t_x"] == 0.05
    assert "base_mix" not in tool.key_params(Parameters.preset("paper"))  # at the paper's 1: off


def test_code_version_is_stable(tool):
    assert tool.code_version() == tool.code_version()
    assert re.fullmatch(r"\S+\+[0-9a-f]{16}", tool.code_version())


@pytest.mark.skipif(not MIT_REAL.is_dir(), reason="shared MIT-Berkeley data not present")
def test_scores_are_cached_and_reused_features_give_fresh_results(tool, tmp_path):
    objects = tool.load_objects(MIT_REAL, "diffuse", names=["teabag2", "phone"])
    assert list(objects) == ["phone", "teabag2"]
    sample, _ = objects["teabag2"]
    base = Parameters().replace(iterations=2, use_sm=False)  # Stage 0 without S_m's similarity
    cache = JsonlCache(tmp_path / "cache")
    score = tool.MITScore(objects, base, cache, "lab", "test")
    first = score({}, "teabag2")
    assert score.features[next(iter(score.features))].similarity is None
    # S_m on: its similarity is computed and merged with the kept features
    for changes in ({"use_sm": True}, {"use_sm": True, "lambda_s": 0.01}):
        got = score(changes, "teabag2")
        p = base.replace(**changes)
        out = decompose(sample.image[None], p, mask=sample.mask[None])
        fresh = mit_lmse(
            sample.reflectance[None],
            sample.shading[None],
            out.reflectance,
            out.shading,
            sample.mask[None],
        ).item()
        assert got == pytest.approx(fresh, rel=1e-6, abs=1e-9)
    assert len(score.features) == 1
    assert score.computed == 3 and len(JsonlCache(tmp_path / "cache")) == 3
    again = tool.MITScore(objects, base, JsonlCache(tmp_path / "cache"), "lab", "test")
    assert again({}, "teabag2") == first and again.computed == 0 and again.reused == 1
    # another code version or input does not reuse the record
    parts = {"params": tool.key_params(base), "object": "teabag2", "input": "lab"}
    parts.update(data=objects["teabag2"][1], threads=torch.get_num_threads())
    assert again.cache.get(JsonlCache.key(**parts, code="test"))["lmse"] == first
    assert again.cache.get(JsonlCache.key(**parts, code="other")) is None


@pytest.mark.skipif(not MIT_REAL.is_dir(), reason="shared MIT-Berkeley data not present")
def test_natural_folders_take_missing_ground_truth_from_the_laboratory_folder(tool, tmp_path):
    for name in ("phone", "teabag2"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "diffuse.png").symlink_to((MIT_REAL / name / "diffuse.png").resolve())
    natural = tool.load_objects(tmp_path, "diffuse", gt_root=MIT_REAL)
    lab = tool.load_objects(MIT_REAL, "diffuse", names=["phone", "teabag2"])
    assert list(natural) == ["phone", "teabag2"]
    assert natural["phone"][1] == lab["phone"][1]  # the same files, the same fingerprint
    with pytest.raises(SystemExit, match="no reflectance.png"):
        tool.load_objects(tmp_path, "diffuse")


def test_references_are_the_papers_values_or_off(tool):
    ref = tool.references(["t_e", "base_mix", "lambda_m", "dark_level", "clip_level"])
    paper = Parameters.preset("paper").to_dict()
    assert ref == {
        "t_e": paper["t_e"],
        "base_mix": paper["base_mix"],
        "lambda_m": paper["lambda_m"],
        "dark_level": 0.0,
        "clip_level": 0.0,
    }
    assert ref["t_e"] != Parameters().to_dict()["t_e"]  # the default's is tuned, not the paper's


def test_nested_prints_the_folds_and_what_went_back(tool, capsys):
    import argparse

    names = ["a", "b", "c", "d", "e", "f"]
    base = {n: 0.01 * (1 + i) for i, n in enumerate(names)}

    def score(changes, sample):  # t_e helps a and b a lot, hurts the rest a little
        if changes.get("t_e", 0.0) == 0.0:
            return base[sample]
        return base[sample] - (0.004 if sample in "ab" else -0.0005)

    args = argparse.Namespace(folds=3, no_loo=False, passes=1)
    out = tool.nested(score, names, {"t_e": [0.015, 0.0]}, {"t_e": 0.015}, args, "lab")
    text = capsys.readouterr().out
    assert "## lab: fit, then send back, 3-fold" in text
    assert "## lab: fit, then send back, leave-one-out" in text
    assert set(out) == {"nested_3-fold", "nested_leave-one-out"}
    three = out["nested_3-fold"]
    assert three["inner_k"] == 2 and three["reference"] == {"t_e": 0.0}
    # folds 1 and 2 train on one of a, b: t_e's gain there is uneven over the inner folds
    # and goes back; fold 3 trains on both, where the gain is the same in each inner fold
    sent_back = [sel["reverted"] for sel in three["selections"]]
    assert sent_back == [("t_e",), ("t_e",), ()]
    assert [f["changes"] for f in three["folds"]] == [{"t_e": 0.0}, {"t_e": 0.0}, {"t_e": 0.015}]
