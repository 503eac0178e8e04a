"""Nested cross-validation of the tuning rule (fit, then send back): synthetic scores."""

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.eval.crossval import kfold_splits
from torchiid.eval.selection import format_nested, nested_cross_validate, select_values

MIT = ["apple", "box", "cup1", "dinosaur", "frog1", "panther", "paper1", "phone", "squirrel"]
MIT.append("teabag2")
BASE = {n: 0.01 * (1 + i) for i, n in enumerate(MIT)}


def counting(score):
    calls = []

    def wrapped(changes, sample):
        calls.append((tuple(sorted(changes.items())), sample))
        return score(changes, sample)

    wrapped.calls = calls
    return wrapped


def test_a_value_that_helps_on_every_sample_is_kept():
    def score(c, s):
        return BASE[s] - 0.001 * (c.get("x", 0) == 1)

    sel = select_values(score, MIT, {"x": [0, 1]}, {"x": 0}, inner_k=5)
    assert sel.fitted == {"x": 1} and sel.changes == {"x": 1} and sel.reverted == ()
    assert sel.train_score == pytest.approx(sum(BASE.values()) / 10 - 0.001)


def uneven(c, s):
    """x = 1: apple and box much better, the eight others a little worse."""
    if c.get("x", 0) != 1:
        return BASE[s]
    return BASE[s] - (0.004 if s in ("apple", "box") else -0.0005)


def test_a_value_that_helps_a_few_samples_goes_back():
    # x = 1 lowers the mean (two samples much better, the others a little worse), but the
    # paired difference over the inner folds is spread wider than the gain
    sel = select_values(uneven, MIT, {"x": [0, 1]}, {"x": 0}, inner_k=5)
    assert sel.fitted == {"x": 1}  # the fit takes it: the mean training score is lower
    assert sel.changes == {"x": 0} and sel.reverted == ("x",)

    # the same gain on every fold is kept
    def even(c, s):
        return BASE[s] - 0.0004 * (c.get("x", 0) == 1)

    assert select_values(even, MIT, {"x": [0, 1]}, {"x": 0}, inner_k=5).reverted == ()


def test_one_value_goes_back_at_a_time_and_the_rest_is_tested_again():
    # x helps on average but unevenly over the folds; y helps only together with x. Sending
    # x back leaves y worse than nothing, so y goes back in the second round
    def score(c, s):
        x, y = c.get("x", 0), c.get("y", 0)
        noise = 0.002 * [1, -1, 1, -1, 0][MIT.index(s) % 5]  # by inner fold
        return BASE[s] + x * (-0.0001 + noise) - 0.0003 * x * y + 0.0001 * y * (1 - x)

    sel = select_values(score, MIT, {"x": [0, 1], "y": [0, 1]}, {"x": 0, "y": 0}, inner_k=5)
    assert sel.fitted == {"x": 1, "y": 1}
    assert sel.reverted == ("x", "y") and sel.changes == {"x": 0, "y": 0}


#: per inner fold (sample index mod 5): an effect that lowers some folds and raises others
SWING = [1, -1, 1, -1, 0]


def effects(table):
    """A score from ``(x, y) -> (mean effect, swing)``: each sample gets mean + swing·SWING."""

    def score(c, s):
        mean, swing = table[(c.get("x", 0), c.get("y", 0))]
        return BASE[s] + mean + swing * SWING[MIT.index(s) % 5]

    return score


def test_the_spread_is_the_standard_error_not_the_standard_deviation():
    # sending x back worsens the mean by 0.0006; the fold differences' sd is 0.001, their
    # standard error 0.001/sqrt(5) = 0.00045: x stays (by the sd it would go back)
    score = effects({(1, 0): (0.0, 0.0), (0, 0): (0.0006, 0.001)})
    sel = select_values(score, MIT, {"x": [1, 0]}, {"x": 0}, inner_k=5, start={"x": 1})
    assert sel.fitted == {"x": 1} and sel.reverted == () and sel.changes == {"x": 1}


def test_a_value_that_changes_nothing_goes_back():
    sel = select_values(effects({(1, 0): (0.0, 0.0), (0, 0): (0.0, 0.0)}), MIT, {"x": [1, 0]},
                        {"x": 0}, inner_k=5, start={"x": 1})  # fmt: skip
    assert sel.fitted == {"x": 1} and sel.reverted == ("x",) and sel.changes == {"x": 0}


def test_the_value_furthest_below_its_spread_goes_back_first_and_alone():
    # both qualify at first (margins −0.00035 for x, −0.00025 for y); once x is back, sending
    # y back too worsens every fold by 0.001: y stays. Sending y first, or both at once, ends
    # elsewhere
    score = effects(
        {
            (1, 1): (0.0, 0.0),
            (0, 1): (0.0001, 0.001),
            (1, 0): (0.0002, 0.001),
            (0, 0): (0.0011, 0.001),
        }
    )
    grid, ref = {"x": [1, 0], "y": [1, 0]}, {"x": 0, "y": 0}
    sel = select_values(score, MIT, grid, ref, inner_k=5, start={"x": 1, "y": 1})
    assert sel.fitted == {"x": 1, "y": 1}
    assert sel.reverted == ("x",) and sel.changes == {"x": 0, "y": 1}
    # the grid's order does not decide it
    sel = select_values(score, MIT, {"y": [1, 0], "x": [1, 0]}, ref, 5, {"x": 1, "y": 1})
    assert sel.reverted == ("x",)


def test_a_reference_that_equals_nothing_still_ends():
    nan = float("nan")
    sel = select_values(lambda c, s: BASE[s], MIT, {"x": [1]}, {"x": nan}, 5, {"x": 1})
    assert sel.reverted == ("x",)  # it changes nothing: sent back once, then left


def test_grid_values_without_a_reference_are_fitted_and_never_sent_back():
    def score(c, s):
        return BASE[s] + 0.01 * (c.get("z", 0) - 2) ** 2 * (1 + MIT.index(s) % 3)

    sel = select_values(score, MIT, {"z": [0, 1, 2]}, {}, inner_k=5)
    assert sel.changes == {"z": 2} and sel.reverted == ()


def test_nested_folds_never_see_their_validation_samples():
    # x = 1 helps every object by the same amount but squirrel, which it ruins
    def score(c, s):
        if c.get("x", 0) != 1:
            return BASE[s]
        return BASE[s] + (0.05 if s == "squirrel" else -0.001)

    fake = counting(score)
    res = nested_cross_validate(fake, MIT, {"x": [0, 1]}, {"x": 0}, k=5, start={"x": 0})
    assert res.inner_k == 4 and res.cv.k == 5
    for fold, sel, (train, val) in zip(
        res.cv.folds, res.selections, kfold_splits(MIT, 5), strict=True
    ):
        assert fold.train == train and fold.validation == val
        # only the fold that holds squirrel out takes x = 1 (an even gain: never sent back)
        assert fold.changes == ({"x": 1} if "squirrel" in val else {"x": 0})
        assert sel.reverted == ()
    sq = next(f for f in res.cv.folds if "squirrel" in f.validation)
    assert sq.validation_score == pytest.approx(
        (BASE["dinosaur"] - 0.001 + BASE["squirrel"] + 0.05) / 2
    )
    assert sq.train_score == pytest.approx(sum(BASE[n] - 0.001 for n in sq.train) / len(sq.train))
    assert len(fake.calls) == len(set(fake.calls))  # every (changes, sample) scored once


def test_leave_one_out_has_leave_one_out_inside_and_bad_k_fails():
    res = nested_cross_validate(lambda c, s: BASE[s], MIT, {"x": [0]}, {"x": 0}, k=10)
    assert res.inner_k == 9 and res.cv.mean_validation == pytest.approx(0.055)
    assert res.cv.gap == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ParameterError, match="inner_k must be from 2 to 8"):
        nested_cross_validate(lambda c, s: 0.0, MIT, {"x": [0]}, {"x": 0}, k=5, inner_k=9)
    with pytest.raises(ParameterError, match="inner_k"):
        select_values(lambda c, s: 0.0, ["a", "b"], {"x": [0]}, {"x": 0}, inner_k=3)
    with pytest.raises(ParameterError, match="1 training sample is too few"):
        nested_cross_validate(lambda c, s: 0.0, ["a", "b"], {"x": [0]}, {"x": 0}, k=2)


def test_format_nested_names_what_was_fitted_and_sent_back():
    res = nested_cross_validate(uneven, MIT, {"x": [0, 1]}, {"x": 0}, k=5)
    text = format_nested(res, "## t")
    assert text.startswith("## t")
    assert "| fold | validation | fitted | sent back | train | validation LMSE |" in text
    assert "| x=1 | x |" in text
    assert "inner folds 4" in text and "mean validation 0.05" in text
