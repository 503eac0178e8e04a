import json
import math
import statistics

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.eval.crossval import (
    JsonlCache,
    coordinate_search,
    cross_validate,
    format_folds,
    format_table,
    kfold_splits,
    memoised,
    reversion_test,
)

MIT = ["apple", "box", "cup1", "dinosaur", "frog1", "panther", "paper1", "phone", "squirrel",
       "teabag2"]  # fmt: skip


def test_kfold_splits_pairs_the_sorted_names_round_robin():
    folds = kfold_splits(list(reversed(MIT)), 5)
    assert [v for _, v in folds] == [
        ("apple", "panther"),
        ("box", "paper1"),
        ("cup1", "phone"),
        ("dinosaur", "squirrel"),
        ("frog1", "teabag2"),
    ]
    for train, val in folds:
        assert not set(train) & set(val)
        assert sorted(train + val) == sorted(MIT)
    # every name is validated exactly once
    assert sorted(n for _, v in folds for n in v) == sorted(MIT)


def test_kfold_with_k_equal_to_n_is_leave_one_out():
    folds = kfold_splits(MIT, len(MIT))
    assert [v for _, v in folds] == [(n,) for n in sorted(MIT)]
    assert all(len(t) == 9 for t, _ in folds)


@pytest.mark.parametrize("k", [1, 11, 0, True, 2.0])
def test_kfold_rejects_bad_k(k):
    with pytest.raises(ParameterError, match="k must be"):
        kfold_splits(MIT, k)


def test_kfold_rejects_duplicate_names():
    with pytest.raises(ParameterError, match="unique"):
        kfold_splits(["a", "a", "b"], 2)


class Counting:
    """A fake score that counts its calls; sample ``s`` has its optimum at ``x = best[s]``."""

    def __init__(self, best):
        self.best = best
        self.calls = []

    def __call__(self, changes, sample):
        self.calls.append((json.dumps(changes, sort_keys=True), sample))
        x = changes.get("x", 0)
        y = changes.get("y", 0)
        return (x - self.best[sample]) ** 2 + (y - 1) ** 2 + 0.01 * len(sample)


def test_coordinate_search_finds_the_mean_optimum_and_scores_each_pair_once():
    score = Counting({"a": 1, "b": 3})
    found = coordinate_search(score, ["a", "b"], {"x": [0, 1, 2, 3, 4], "y": [0, 1, 2]})
    assert found.changes == {"x": 2, "y": 1}
    assert found.score == pytest.approx(1.0 + 0.01)
    assert len(score.calls) == len(set(score.calls))


def test_coordinate_search_keeps_the_current_value_on_ties_and_starts_from_start():
    flat = lambda c, s: 1.0  # noqa: E731
    assert coordinate_search(flat, ["a"], {"x": [5, 6]}).changes == {}
    assert coordinate_search(flat, ["a"], {"x": [5, 6]}, start={"x": 6}).changes == {"x": 6}


def test_coordinate_search_passes_matter_for_coupled_parameters():
    # the best y depends on x; after x moves, a second pass improves y
    def coupled(c, s):
        x, y = c.get("x", 0), c.get("y", 0)
        return (x - 2) ** 2 + 0.5 * (y - x) ** 2 + 0.3 * (x - y) * x

    grid = {"y": [0, 1, 2], "x": [0, 1, 2]}
    one = coordinate_search(coupled, ["a"], grid, passes=1)
    three = coordinate_search(coupled, ["a"], grid, passes=3)
    assert three.score < one.score
    assert one.passes == 1 and three.passes >= 2
    # a pass that changes nothing ends the search early
    assert coordinate_search(coupled, ["a"], grid, passes=50).passes < 50


@pytest.mark.parametrize(
    "grid", [{"x": []}, {"x": "ab"}, {"x": 3}], ids=["empty", "string", "number"]
)
def test_coordinate_search_rejects_bad_grids(grid):
    with pytest.raises(ParameterError, match="non-empty list"):
        coordinate_search(lambda c, s: 0.0, ["a"], grid)


def test_cross_validate_chooses_on_training_and_scores_on_validation():
    # four samples prefer x = 0, one prefers x = 10: its fold chooses 0 and does badly
    best = {"a": 0, "b": 0, "c": 0, "d": 0, "e": 10}
    score = Counting(best)
    cv = cross_validate(score, list(best), {"x": [0, 10]}, k=5, start={"x": 0})
    by_val = {f.validation: f for f in cv.folds}
    assert by_val[("e",)].changes == {"x": 0}
    assert by_val[("e",)].validation_score == pytest.approx(100 + 1 + 0.01)
    for name in "abcd":
        fold = by_val[(name,)]
        assert fold.validation_score == pytest.approx(1.01)
        # trained on three samples at 0 and e at 10: x = 0 costs 100/4, x = 10 costs 300/4
        assert fold.train_score == pytest.approx(100 / 4 + 1.01)
    vals = [f.validation_score for f in cv.folds]
    assert cv.mean_validation == pytest.approx(statistics.mean(vals))
    assert cv.sd_validation == pytest.approx(statistics.stdev(vals))
    assert cv.se_validation == pytest.approx(statistics.stdev(vals) / math.sqrt(5))
    assert cv.mean_train == pytest.approx(statistics.mean(f.train_score for f in cv.folds))
    assert cv.gap == pytest.approx((cv.mean_validation - cv.mean_train) / cv.mean_train)
    assert cv.sample_scores["e"] == pytest.approx(101.01)
    assert cv.sample_changes["e"] == {"x": 0}


def test_cross_validate_without_a_grid_gives_the_overall_mean_and_no_gap():
    per = {n: 0.01 * (i + 1) for i, n in enumerate(MIT)}
    cv = cross_validate(lambda c, s: per[s], MIT, {}, k=5)
    assert cv.mean_validation == pytest.approx(statistics.mean(per.values()))
    assert cv.gap == pytest.approx(0.0, abs=1e-12)
    assert all(f.changes == {} for f in cv.folds)


def test_memoised_score_is_shared_between_kfold_and_leave_one_out():
    score = Counting({n: i % 3 for i, n in enumerate(MIT)})
    memo = memoised(score)
    cross_validate(memo, MIT, {"x": [0, 1, 2]}, k=5)
    first = len(score.calls)
    cross_validate(memo, MIT, {"x": [0, 1, 2]}, k=10)
    coordinate_search(memo, MIT, {"x": [0, 1, 2]})
    # every (x, sample) pair was already scored by the 5 folds, whose training sets cover all
    assert len(score.calls) == first == len(set(score.calls))
    assert memoised(memo) is memo


def test_reversion_test_measures_the_change_and_the_fold_choice():
    base = {n: 0.01 * (1 + i) for i, n in enumerate(MIT)}  # large spread over objects

    def score(c, s):
        if c.get("v") == "paper":
            return base[s] + 0.01  # worse everywhere, by less than the spread of the folds
        if c.get("w") == "paper":
            return base[s] - 0.001  # better everywhere
        return base[s]

    rows = reversion_test(score, MIT, {"v": {"v": "paper"}, "w": {"w": "paper"}}, k=5)
    v, w = rows
    assert v.delta == pytest.approx(0.01) and w.delta == pytest.approx(-0.001)
    assert v.worse == 10 and w.worse == 0
    assert v.picks_b == (False,) * 5 and w.picks_b == (True,) * 5
    assert v.choice_validation == pytest.approx(statistics.mean(base.values()))
    assert w.choice_validation == pytest.approx(statistics.mean(base.values()) - 0.001)
    assert v.se_paired == pytest.approx(0.0, abs=1e-12)
    folds = [statistics.mean(base[n] for n in val) for _, val in kfold_splits(MIT, 5)]
    assert v.sd == pytest.approx(statistics.stdev(folds))
    # fold means 0.035 ... 0.075: sd 0.0158 > 0.01 > se = sd / sqrt(5) = 0.0071
    assert v.reverts("sd") and v.sd > 0.01
    assert not v.reverts("se")
    assert not v.reverts("paired")  # worse on every object by the same amount
    assert w.reverts("sd") and w.reverts("se") and w.reverts("paired")
    with pytest.raises(ParameterError, match="spread"):
        v.reverts("iqr")


def test_format_table_and_folds():
    text = format_table(["a", "b", "c"], [["x", 0.123456, 3], ["y", float("nan"), "z"]])
    assert text.splitlines() == [
        "| a | b | c |",
        "| --- | --- | --- |",
        "| x | 0.12346 | 3 |",
        "| y | nan | z |",
    ]
    with pytest.raises(ParameterError, match="2 cells for 3 columns"):
        format_table(["a", "b", "c"], [["x", 1]])
    cv = cross_validate(lambda c, s: 0.02 if s == "a" else 0.01, ["a", "b", "c", "d"], {}, 2)
    out = format_folds(cv, "## title")
    assert out.startswith("## title")
    assert "| 1 | a c | (as given) | 0.01000 | 0.01500 |" in out
    assert "mean validation 0.01250 ± 0.00354 (sd over 2 folds; se 0.00250)" in out


def test_jsonl_cache_round_trip_and_torn_lines(tmp_path):
    key = JsonlCache.key(params={"b": 1, "a": 2.5}, object="apple")
    assert key == JsonlCache.key(object="apple", params={"a": 2.5, "b": 1})
    assert key != JsonlCache.key(params={"b": 1, "a": 2.5}, object="box")
    cache = JsonlCache(tmp_path / "c")
    cache.put(key, {"lmse": 0.01})
    with (tmp_path / "c" / "scores.jsonl").open("a") as f:
        f.write('{"key": "torn", "lms')  # a run killed mid-line
    again = JsonlCache(tmp_path / "c")
    assert len(again) == 1
    assert again.get(key) == {"lmse": 0.01, "key": key}
    assert again.get("torn") is None
    memory = JsonlCache(None)
    memory.put("k", {"x": 1})
    assert memory.get("k")["x"] == 1 and memory.path is None
