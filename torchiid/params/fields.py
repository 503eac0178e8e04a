"""One declaration per parameter: its default, documentation, valid range and schedule.

Every leaf field of the parameter groups is made by :func:`param`, whose ``metadata`` holds

* ``"doc"``: the meaning, one line;
* ``"paper"``: the paper's value, or ``None`` where the paper gives none;
* ``"valid"``: the valid range as text (``"> 0"``, ``">= 0"``, ``"in [0, 1]"``,
  ``"one of a, b"``, ...), which is also what :func:`check_fields` enforces;
* ``"why"`` (tuned values only): why the default differs from the paper, one short fact;
* ``"schedule"`` (weights only): ``"× τ"`` or ``"÷ τ"``, the weight's step from one
  alternation to the next (§3.4), applied by :meth:`ParameterGroup.step`.

The documentation is generated from these fields (:func:`dataclasses.fields`), so a value's
meaning, range and history of tuning are stated once, next to it.
"""

import dataclasses
import math
import numbers
import types
from typing import Any, ClassVar

from torchiid.core.exceptions import ParameterError

__all__ = [
    "param",
    "switch",
    "check_fields",
    "ParameterGroup",
    "StageGroup",
    "SCHEDULE_UP",
    "SCHEDULE_DOWN",
]

#: ``metadata["schedule"]`` of a weight multiplied by τ at each alternation
SCHEDULE_UP = "× τ"
#: ``metadata["schedule"]`` of a weight divided by τ at each alternation
SCHEDULE_DOWN = "÷ τ"


def param(
    default: Any,
    doc: str,
    *,
    valid: str,
    paper: Any = None,
    why: str | None = None,
    schedule: str | None = None,
) -> Any:
    """A parameter field: ``dataclasses.field`` with the documentation in its metadata."""
    metadata: dict[str, Any] = {"doc": doc, "paper": paper, "valid": valid}
    if why is not None:
        metadata["why"] = why
    if schedule is not None:
        if schedule not in (SCHEDULE_UP, SCHEDULE_DOWN):
            raise ValueError(f"schedule must be {SCHEDULE_UP!r} or {SCHEDULE_DOWN!r}")
        metadata["schedule"] = schedule
    return dataclasses.field(default=default, metadata=metadata)


def switch(what: str, note: str = "ablations") -> Any:
    """The field of a switch of ``what`` (a prior or a whole stage): on, as in the paper.

    Every switch is this one declaration, so the ablations and baselines turn the method's
    parts off alike; ``note`` says what turning it off gives.
    """
    return param(True, f"switch of {what} ({note})", paper=True, valid="true or false")


# valid text -> (test, what the error message says the value must be); a ``valid`` text may
# add a remark after "; " (documentation only, checked by its group)
#: the largest float32 value: a parameter beyond it overflows the solvers' float32 tensors
FLOAT32_MAX = 3.4028234663852886e38

_RULES: dict[str, tuple[Any, str]] = {
    "> 0": (lambda v: v > 0, "> 0"),
    ">= 0": (lambda v: v >= 0, ">= 0"),
    "in [0, 1]": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "in (0, 1]": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "odd, >= 3": (lambda v: v >= 3 and v % 2 == 1, "odd and >= 3"),
    ">= 0 or null": (lambda v: v is None or v >= 0, "a number >= 0 or null"),
    "true or false": (lambda v: True, "true or false"),
    "any integer": (lambda v: True, "an integer"),
}


def _rule(valid: str) -> tuple[Any, str]:
    text = valid.split("; ")[0]
    if text.startswith("one of "):
        choices = text[len("one of ") :].split(", ")
        return (lambda v: v in choices), text
    return _RULES[text]


def _shown(value: Any) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def _typed(obj: object, f: dataclasses.Field, value: Any, must: str) -> Any:
    """``value`` as the field's type (ints as floats for float fields), or a ParameterError."""
    kind = f.type
    optional = isinstance(kind, types.UnionType) and type(None) in kind.__args__
    if optional:
        if value is None:
            return None
        kind = next(k for k in kind.__args__ if k is not type(None))
    if kind is bool and not isinstance(value, bool):
        raise ParameterError(f"parameter {f.name} must be true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise ParameterError(f"parameter {f.name} must be an integer, got {value!r}")
        return int(value)  # NumPy's integers too
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            what = must if optional else "a number"
            raise ParameterError(f"parameter {f.name} must be {what}, got {value!r}")
        value = float(value)
        if math.isinf(value) or abs(value) > FLOAT32_MAX:  # NaN: the range rules refuse it
            raise ParameterError(
                f"parameter {f.name} must be a finite number within float32's range "
                f"(|x| <= {FLOAT32_MAX:.3g}; the solvers compute in float32), got {value!r}"
            )
        return value
    return value


def check_fields(obj: object) -> None:
    """Check every leaf field of ``obj`` against its type and ``metadata["valid"]``.

    Float fields given as integers become floats. NaN fails every range.

    Raises:
        ParameterError: naming the field and the bad value.
    """
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        if "valid" not in f.metadata:  # a group: it checks itself
            continue
        test, must = _rule(f.metadata["valid"])
        value = _typed(obj, f, getattr(obj, f.name), must)
        object.__setattr__(obj, f.name, value)
        if not test(value):
            raise ParameterError(f"parameter {f.name} must be {must}, got {_shown(value)}")


@dataclasses.dataclass(frozen=True)
class ParameterGroup:
    """Base of the parameter groups: checked on construction, copied by :meth:`replace`."""

    def __post_init__(self) -> None:
        check_fields(self)
        self._check()

    def _check(self) -> None:
        """Checks that involve several fields (none by default)."""

    def replace(self, **changes: Any) -> "ParameterGroup":
        """A copy with some fields changed (unknown names rejected)."""
        known = {f.name for f in dataclasses.fields(self)}
        for key in changes:
            if key not in known:
                raise ParameterError(f"Invalid parameter: {key}")
        return dataclasses.replace(self, **changes)

    def step(self, tau: float) -> "ParameterGroup":
        """The next alternation's copy (§3.4): each weight ``× τ`` or ``÷ τ`` (its schedule)."""
        if not tau > 0:
            raise ParameterError(f"the schedule's tau must be > 0, got {tau}")
        changes = {}
        for f in dataclasses.fields(self):
            rule = f.metadata.get("schedule")
            if rule == SCHEDULE_UP:
                changes[f.name] = getattr(self, f.name) * tau
            elif rule == SCHEDULE_DOWN:
                changes[f.name] = getattr(self, f.name) / tau
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class StageGroup(ParameterGroup):
    """Base of the groups of the two stages, whose priors each have a weight and a switch."""

    #: prior -> (its weight field, its switch field or ``None`` where it has none)
    _PRIORS: ClassVar[dict[str, tuple[str, str | None]]]
    #: the field that switches the whole stage
    _STAGE: ClassVar[str]

    def weights(self) -> dict[str, float]:
        """Each prior's weight, by the prior's name.

        0 where a switch turns the prior or the stage off: the one place the switches act.
        """
        on = getattr(self, self._STAGE)
        return {
            name: getattr(self, weight) if on and (switch is None or getattr(self, switch)) else 0.0
            for name, (weight, switch) in self._PRIORS.items()
        }

    @property
    def active(self) -> bool:
        """Whether any prior is on (else the stage is skipped)."""
        return any(w > 0 for w in self.weights().values())
