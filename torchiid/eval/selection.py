"""Nested cross-validation of a tuning rule: fit, then send back what earns no place.

:func:`~torchiid.eval.crossval.cross_validate` refits a grid on each fold's training samples
and scores the fit on the fold's validation samples: it estimates what *fitting* the values
gives on unseen samples. A preset's values that depart from the paper are tested by a longer
rule, and this module runs that rule where a fold's validation samples take no part (nested
cross-validation):

1. **Fit** (:func:`~torchiid.eval.crossval.coordinate_search`): on the training samples each
   grid parameter in turn takes the candidate with the lowest mean score.
2. **Send back** (the reversion rule): a fitted value that differs from its reference (the
   paper's value, or the value that turns an addition off) goes back to the reference unless
   that worsens the mean training score by more than the standard error, over an inner split
   of the training samples into folds, of the paired difference (``se(B − A)``). One value goes
   back at a time, the one whose worsening lies furthest below its spread (on a tie, the first
   in the grid's order), and the test runs again on what is left until nothing more goes back;
   a value that changes nothing (no worsening, no spread) goes back.

:func:`select_values` is the rule on one set of samples; :func:`nested_cross_validate` runs it
on each outer fold's training samples (its inner folds split those samples alone, as
:func:`~torchiid.eval.crossval.kfold_splits` does) and scores the result on the fold's
validation samples. What the validation samples take no part in is this rule; the grid's
candidates and the ``start`` it searches from are the caller's, and were they chosen on all
the samples (as a preset's tuned values were), the estimate does not undo that choice. When
every fold ends at the same values, the mean training and validation scores are equal by
construction (each sample is in ``k − 1`` training sets), so the gap says nothing then; the
news is that the folds agree. Scores are cached as in :mod:`torchiid.eval.crossval`: a score
function is called once per distinct ``(changes, sample)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from torchiid.core.exceptions import ParameterError
from torchiid.eval.crossval import (
    CrossValidation,
    Fold,
    Score,
    coordinate_search,
    format_table,
    kfold_splits,
    memoised,
)

__all__ = ["NestedCrossValidation", "Selection", "format_nested", "nested_cross_validate"]
__all__ += ["select_values"]


@dataclass(frozen=True)
class Selection:
    """What :func:`select_values` chose on one set of samples.

    Attributes:
        changes: the values kept (``start`` updated by the grid's parameters).
        fitted: the values the fit chose, before any went back.
        reverted: the parameters sent back to their reference, in the order they went.
        train_score: the mean score of ``changes`` over the samples.
    """

    changes: dict[str, Any]
    fitted: dict[str, Any]
    reverted: tuple[str, ...]
    train_score: float


def _mean(score: Score, changes: Mapping[str, Any], samples: Sequence[str]) -> float:
    return sum(score(changes, s) for s in samples) / len(samples)


def _paired_se(diffs: Sequence[float]) -> float:
    m = sum(diffs) / len(diffs)
    return math.sqrt(sum((d - m) ** 2 for d in diffs) / (len(diffs) - 1) / len(diffs))


def select_values(
    score: Score,
    samples: Sequence[str],
    grid: Mapping[str, Sequence[Any]],
    reference: Mapping[str, Any],
    inner_k: int,
    start: Mapping[str, Any] | None = None,
    passes: int = 1,
) -> Selection:
    """The tuning rule on ``samples``: fit the grid, then send back what does not earn its place.

    Args:
        score: ``score(changes, sample)``, lower is better.
        samples: the samples the rule sees.
        grid: candidate values per parameter (the fit's search order).
        reference: the value each parameter goes back to (e.g. the paper's); a grid parameter
            without one is fitted and never sent back.
        inner_k: the folds the samples are split into for the spread of a difference.
        start: the values the fit starts from: the preset's value of every grid parameter. A
            parameter the fit leaves at the base's value, not named here, is not sent back
            (its value is not known here).
        passes: coordinate-search passes.

    Example:
        >>> s = lambda c, n: {"a": 1.0, "b": 3.0}[n] + c.get("x", 0) * (-1 if n == "a" else 0.5)
        >>> select_values(s, ["a", "b"], {"x": [0, 1]}, {"x": 0}, 2).changes  # fit 1, sent back
        {'x': 0}
    """
    if not 2 <= inner_k <= len(samples):
        raise ParameterError(f"inner_k must be from 2 to {len(samples)}, got {inner_k!r}")
    memo = memoised(score)
    fitted = coordinate_search(memo, samples, grid, start, passes).changes
    inner = [val for _, val in kfold_splits(samples, inner_k)]
    current, reverted = dict(fitted), []
    while True:
        best: tuple[float, str] | None = None
        for name in grid:
            if name not in reference or name not in current or name in reverted:
                continue
            if current[name] == reference[name]:
                continue
            back = {**current, name: reference[name]}
            diffs = [_mean(memo, back, v) - _mean(memo, current, v) for v in inner]
            delta = _mean(memo, back, samples) - _mean(memo, current, samples)
            margin = delta - _paired_se(diffs)
            if margin <= 0 and (best is None or margin < best[0]):  # a tie: the grid's order
                best = (margin, name)
        if best is None:
            break
        current = {**current, best[1]: reference[best[1]]}
        reverted.append(best[1])
    return Selection(current, fitted, tuple(reverted), _mean(memo, current, samples))


@dataclass(frozen=True)
class NestedCrossValidation:
    """:func:`nested_cross_validate`'s result.

    Attributes:
        cv: the outer folds (each fold's ``changes`` are what the rule kept on its training
            samples) and their summary figures.
        selections: each outer fold's :class:`Selection`.
        inner_k: the inner folds' number.
    """

    cv: CrossValidation
    selections: tuple[Selection, ...]
    inner_k: int


def nested_cross_validate(
    score: Score,
    samples: Sequence[str],
    grid: Mapping[str, Sequence[Any]],
    reference: Mapping[str, Any],
    k: int,
    inner_k: int | None = None,
    start: Mapping[str, Any] | None = None,
    passes: int = 1,
) -> NestedCrossValidation:
    """``k``-fold cross-validation of :func:`select_values` (fit, then send back).

    ``inner_k`` defaults to ``k − 1`` folds of each outer fold's training samples (at most one
    per sample): with ten samples and ``k`` 5, the rule sees eight samples in four folds of
    two, as it sees ten in five folds of two when the preset is chosen.
    """
    memo = memoised(score)
    splits = kfold_splits(samples, k)
    n_train = min(len(train) for train, _ in splits)
    if n_train < 2:
        raise ParameterError(f"a fold's {n_train} training sample is too few for inner folds")
    inner = min(k - 1, n_train) if inner_k is None else inner_k
    if not 2 <= inner <= n_train:
        raise ParameterError(f"inner_k must be from 2 to {n_train}, got {inner!r}")
    folds, selections = [], []
    for j, (train, val) in enumerate(splits):
        chosen = select_values(memo, train, grid, reference, inner, start, passes)
        scores = {s: memo(chosen.changes, s) for s in val}
        mean_val = sum(scores.values()) / len(val)
        folds.append(Fold(j, train, val, chosen.changes, chosen.train_score, mean_val, scores))
        selections.append(chosen)
    cv = CrossValidation(tuple(folds), {n: list(v) for n, v in grid.items()})
    return NestedCrossValidation(cv, tuple(selections), inner)


def _shown(changes: Mapping[str, Any], names: Sequence[str]) -> str:
    return ", ".join(f"{n}={changes[n]}" for n in names if n in changes) or "(as given)"


def format_nested(result: NestedCrossValidation, title: str) -> str:
    """The per-fold table (fitted, sent back, kept, scores) and the summary line."""
    cv, names = result.cv, list(result.cv.grid)
    rows = [
        [
            f.index + 1,
            " ".join(f.validation),
            _shown(s.fitted, names),
            ", ".join(s.reverted) or "none",
            f.train_score,
            f.validation_score,
        ]
        for f, s in zip(cv.folds, result.selections, strict=True)
    ]
    header = ["fold", "validation", "fitted", "sent back", "train", "validation LMSE"]
    summary = (
        f"mean validation {cv.mean_validation:.5f} ± {cv.sd_validation:.5f} (sd over "
        f"{cv.k} folds; se {cv.se_validation:.5f}), mean train {cv.mean_train:.5f}, "
        f"gap {100 * cv.gap:+.1f}%; inner folds {result.inner_k}"
    )
    return f"{title}\n\n{format_table(header, rows)}\n\n{summary}"
