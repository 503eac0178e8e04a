"""Cross-validation of parameter choices: fixed folds, a coordinate search, a score cache, tables.

The method's parameters are chosen on a handful of images (the MIT-Berkeley objects); a choice
that only fits those images shows as a gap between the score on the images it was chosen on and
the score on images it was not. :func:`cross_validate` measures that gap:

- The samples are split into ``k`` fixed folds (:func:`kfold_splits`): with the names sorted,
  fold ``j`` holds names ``j, j + k, j + 2k, …`` (round robin), so the split depends on the
  names alone. ``k`` equal to the number of samples is leave-one-out.
- On each fold's training samples, :func:`coordinate_search` picks the parameter values: each
  parameter of the grid in turn takes the candidate with the lowest mean training score (the
  current value is a candidate too, and a tie keeps it), for a fixed number of passes (fewer
  when a pass changes nothing). An empty grid fits nothing: the configuration is scored as
  given.
- The chosen values are scored on the fold's validation samples.

A score is any ``score(changes, sample) -> float`` (lower is better), ``changes`` a mapping of
parameter names to values over a fixed base; it is called at most once per distinct
``(changes, sample)`` within a run, and :class:`JsonlCache` keeps such scores on disk between
runs. The figures: the mean over folds of the fold's mean validation score, its spread as the
standard deviation over folds (``sd``, ``n − 1`` in the denominator) and as the standard error
of the mean (``se = sd / √k``), the mean training score, and the relative gap
``(validation − train) / train``. The folds have equal sizes when ``k`` divides the number of
samples, and then the mean validation score is the mean over samples.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from torchiid.core.exceptions import ParameterError
from torchiid.eval.score_cache import JsonlCache

__all__ = [
    "CrossValidation",
    "Fold",
    "JsonlCache",
    "Reversion",
    "Search",
    "coordinate_search",
    "cross_validate",
    "format_folds",
    "format_table",
    "kfold_splits",
    "memoised",
    "reversion_test",
]

Score = Callable[[Mapping[str, Any], str], float]


def kfold_splits(names: Sequence[str], k: int) -> list[tuple[tuple[str, ...], tuple[str, ...]]]:
    """Fixed ``k``-fold split: ``(train, validation)`` per fold, fold ``j`` = sorted names ``j::k``.

    Example:
        >>> kfold_splits(["d", "a", "c", "b"], 2)[0]
        (('b', 'd'), ('a', 'c'))
    """
    ordered = sorted(names)
    if len(set(ordered)) != len(ordered):
        raise ParameterError("sample names must be unique")
    if not isinstance(k, int) or isinstance(k, bool) or not 2 <= k <= len(ordered):
        raise ParameterError(f"k must be an integer from 2 to {len(ordered)}, got {k!r}")
    out = []
    for j in range(k):
        val = tuple(ordered[j::k])
        out.append((tuple(n for n in ordered if n not in val), val))
    return out


def _key(changes: Mapping[str, Any]) -> str:
    return json.dumps(dict(changes), sort_keys=True)


def _check_grid(grid: Mapping[str, Sequence[Any]]) -> None:
    for name, values in grid.items():
        if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or not values:
            raise ParameterError(f"grid entry {name!r} must be a non-empty list of values")


@dataclass(frozen=True)
class Search:
    """Result of :func:`coordinate_search`.

    Attributes:
        changes: the chosen values (``start`` updated by the grid's parameters).
        score: their mean score over the samples searched on.
        passes: passes run (the last may have changed nothing).
    """

    changes: dict[str, Any]
    score: float
    passes: int


class _Memo:
    """``score`` called at most once per ``(changes, sample)``."""

    def __init__(self, score: Score) -> None:
        self.score = score
        self.seen: dict[tuple[str, str], float] = {}

    def __call__(self, changes: Mapping[str, Any], sample: str) -> float:
        key = (_key(changes), sample)
        if key not in self.seen:
            self.seen[key] = float(self.score(dict(changes), sample))
        return self.seen[key]


def _mean(score: Score, changes: Mapping[str, Any], samples: Sequence[str]) -> float:
    return sum(score(changes, s) for s in samples) / len(samples)


def memoised(score: Score) -> Score:
    """``score`` wrapped so that repeated ``(changes, sample)`` pairs are computed once.

    Pass the same wrapped score to several :func:`cross_validate` calls (k-fold, then
    leave-one-out) to share their evaluations.
    """
    return score if isinstance(score, _Memo) else _Memo(score)


def coordinate_search(
    score: Score,
    samples: Sequence[str],
    grid: Mapping[str, Sequence[Any]],
    start: Mapping[str, Any] | None = None,
    passes: int = 2,
) -> Search:
    """Choose the grid values with the lowest mean score on ``samples``, one parameter at a time.

    Args:
        score: ``score(changes, sample)``, lower is better.
        samples: the samples the mean is taken over.
        grid: candidate values per parameter, searched in this order.
        start: the values the search starts from (``{}``: the base's).
        passes: passes over the grid; the search stops sooner when a pass changes nothing.

    Example:
        >>> f = lambda c, s: (c.get("x", 0) - 2) ** 2 + (c.get("y", 0) - 1) ** 2
        >>> coordinate_search(f, ["a"], {"x": [0, 1, 2, 3], "y": [0, 1, 2]}, passes=3).changes
        {'x': 2, 'y': 1}
    """
    _check_grid(grid)
    if not samples:
        raise ParameterError("coordinate search needs at least one sample")
    if passes < 1:
        raise ParameterError(f"passes must be >= 1, got {passes}")
    memo = memoised(score)
    current = dict(start or {})
    best = _mean(memo, current, samples)
    done = 0
    for _ in range(passes):
        done += 1
        changed = False
        for name, values in grid.items():
            for value in values:
                if name in current and current[name] == value:
                    continue
                trial = {**current, name: value}
                s = _mean(memo, trial, samples)
                if s < best:
                    best, current, changed = s, trial, True
        if not changed:
            break
    return Search(current, best, done)


@dataclass(frozen=True)
class Fold:
    """One fold of :func:`cross_validate`.

    Attributes:
        index: the fold's number (0-based).
        train: its training samples.
        validation: its validation samples.
        changes: the values chosen on ``train``.
        train_score: their mean score on ``train``.
        validation_score: their mean score on ``validation``.
        scores: their score on each validation sample.
    """

    index: int
    train: tuple[str, ...]
    validation: tuple[str, ...]
    changes: dict[str, Any]
    train_score: float
    validation_score: float
    scores: dict[str, float]


def _sd(values: Sequence[float]) -> float:
    if len(values) < 2:
        return float("nan")
    m = sum(values) / len(values)
    return math.sqrt(sum((v - m) ** 2 for v in values) / (len(values) - 1))


@dataclass(frozen=True)
class CrossValidation:
    """The folds of one cross-validation and its summary figures (see the module docstring)."""

    folds: tuple[Fold, ...]
    grid: dict[str, list[Any]]

    @property
    def k(self) -> int:
        """Number of folds."""
        return len(self.folds)

    @property
    def mean_validation(self) -> float:
        """Mean over folds of the fold's mean validation score."""
        return sum(f.validation_score for f in self.folds) / self.k

    @property
    def sd_validation(self) -> float:
        """Standard deviation over folds of the fold's validation score (``n − 1``)."""
        return _sd([f.validation_score for f in self.folds])

    @property
    def se_validation(self) -> float:
        """Standard error of :attr:`mean_validation`: ``sd / √k``."""
        return self.sd_validation / math.sqrt(self.k)

    @property
    def mean_train(self) -> float:
        """Mean over folds of the fold's training score."""
        return sum(f.train_score for f in self.folds) / self.k

    @property
    def gap(self) -> float:
        """Relative train–validation gap ``(validation − train) / train``."""
        return (self.mean_validation - self.mean_train) / self.mean_train

    @property
    def sample_scores(self) -> dict[str, float]:
        """Each sample's validation score (from the fold that held it out)."""
        return {s: v for f in self.folds for s, v in f.scores.items()}

    @property
    def sample_changes(self) -> dict[str, dict[str, Any]]:
        """The values each sample was validated with."""
        return {s: f.changes for f in self.folds for s in f.validation}


def cross_validate(
    score: Score,
    samples: Sequence[str],
    grid: Mapping[str, Sequence[Any]],
    k: int,
    start: Mapping[str, Any] | None = None,
    passes: int = 2,
) -> CrossValidation:
    """``k``-fold cross-validation of :func:`coordinate_search` over ``grid``.

    ``score`` is called once per distinct ``(changes, sample)`` (memoised over the folds);
    for an empty grid each fold scores ``start`` as it is.
    """
    _check_grid(grid)
    memo = memoised(score)
    folds = []
    for j, (train, val) in enumerate(kfold_splits(samples, k)):
        found = coordinate_search(memo, train, grid, start, passes)
        scores = {s: memo(found.changes, s) for s in val}
        folds.append(
            Fold(j, train, val, found.changes, found.score, sum(scores.values()) / len(val), scores)
        )
    return CrossValidation(tuple(folds), {n: list(v) for n, v in grid.items()})


@dataclass(frozen=True)
class Reversion:
    """One configuration change tested by :func:`reversion_test` (A: as given, B: changed).

    Attributes:
        name: the test's label.
        changes: B's values (e.g. the paper's).
        score_a: A's mean score over the samples.
        score_b: B's mean score over the samples.
        sd: standard deviation over the folds of A's validation score.
        se: standard error of A's mean validation score, ``sd / √k``.
        se_paired: standard error over the folds of the fold's mean of ``B − A``.
        worse: samples on which B scores higher (worse) than A.
        picks_b: per fold, whether the training samples chose B (a lower mean; a tie keeps A).
        choice_validation: mean over folds of the validation score of each fold's choice.
    """

    name: str
    changes: dict[str, Any]
    score_a: float
    score_b: float
    sd: float
    se: float
    se_paired: float
    worse: int
    picks_b: tuple[bool, ...]
    choice_validation: float

    @property
    def delta(self) -> float:
        """``B − A``: how much the change worsens the mean score (negative: improves)."""
        return self.score_b - self.score_a

    def reverts(self, spread: str = "sd") -> bool:
        """Whether B worsens the mean score by no more than a spread.

        ``spread``: ``"sd"`` (of A's validation score over the folds), ``"se"`` (its standard
        error) or ``"paired"`` (the standard error of ``B − A`` over the folds, which leaves
        out how much harder some samples are than others).
        """
        limits = {"sd": self.sd, "se": self.se, "paired": self.se_paired}
        if spread not in limits:
            raise ParameterError(f"spread must be 'sd', 'se' or 'paired', got {spread!r}")
        return self.delta <= limits[spread]


def reversion_test(
    score: Score,
    samples: Sequence[str],
    tests: Mapping[str, Mapping[str, Any]],
    k: int,
) -> list[Reversion]:
    """For each labelled change (e.g. a tuned value set back to the paper's), A against B.

    A is the configuration as given (``{}``), B the change. Both are scored on every sample;
    per fold of :func:`kfold_splits`, the choice between them is made on the training samples
    (the grid of two) and scored on the validation samples.
    """
    memo = memoised(score)
    base = cross_validate(memo, samples, {}, k)
    out = []
    for name, changes in tests.items():
        changes = dict(changes)
        diffs, picks, chosen = [], [], []
        for train, val in kfold_splits(samples, k):
            diffs.append(_mean(memo, changes, val) - _mean(memo, {}, val))
            pick = _mean(memo, changes, train) < _mean(memo, {}, train)
            picks.append(pick)
            chosen.append(_mean(memo, changes if pick else {}, val))
        worse = sum(memo(changes, s) > memo({}, s) for s in samples)
        out.append(
            Reversion(
                name,
                changes,
                _mean(memo, {}, samples),
                _mean(memo, changes, samples),
                base.sd_validation,
                base.se_validation,
                _sd(diffs) / math.sqrt(k),
                worse,
                tuple(picks),
                sum(chosen) / k,
            )
        )
    return out


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.5f}" if value == value else "nan"
    return str(value)


def format_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table (floats with 5 decimals), as the README's tables.

    Example:
        >>> print(format_table(["a", "b"], [["x", 0.5]]))
        | a | b |
        | --- | --- |
        | x | 0.50000 |
    """
    for row in rows:
        if len(row) != len(header):
            raise ParameterError(f"a row has {len(row)} cells for {len(header)} columns: {row}")
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    lines += ["| " + " | ".join(_fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _changes_text(changes: Mapping[str, Any], grid: Mapping[str, Any]) -> str:
    shown = {n: changes[n] for n in grid if n in changes}
    return ", ".join(f"{n}={v}" for n, v in shown.items()) or "(as given)"


def format_folds(cv: CrossValidation, title: str) -> str:
    """The per-fold table and the summary lines of one cross-validation."""
    rows = [
        [
            f.index + 1,
            " ".join(f.validation),
            _changes_text(f.changes, cv.grid),
            f.train_score,
            f.validation_score,
        ]
        for f in cv.folds
    ]
    table = format_table(["fold", "validation", "chosen", "train", "validation LMSE"], rows)
    summary = (
        f"mean validation {cv.mean_validation:.5f} ± {cv.sd_validation:.5f} (sd over "
        f"{cv.k} folds; se {cv.se_validation:.5f}), mean train {cv.mean_train:.5f}, "
        f"gap {100 * cv.gap:+.1f}%"
    )
    return f"{title}\n\n{table}\n\n{summary}"
