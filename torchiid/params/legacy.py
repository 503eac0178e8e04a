"""The stages' configuration objects of torchiid 0.x, deprecated for one minor version.

``ShadingWeights`` / ``ShadingOptions`` and ``ReflectanceWeights`` / ``ReflectanceOptions``
split each stage's configuration in two and repeated :class:`~torchiid.params.Parameters`;
the stages now take one parameter group (:class:`~torchiid.params.ShadingParameters`,
:class:`~torchiid.params.ReflectanceParameters`). Reading these names from
:mod:`torchiid.stages` or :mod:`torchiid.stages.config`, the ``Parameters`` methods that built
them and the stage calls that take them warn with a ``DeprecationWarning`` naming the
replacement, and work as before.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, TypeVar, cast

from torchiid.core.exceptions import ParameterError
from torchiid.params.reflectance import ReflectanceParameters
from torchiid.params.shading import ShadingParameters

__all__ = [
    "ShadingWeights",
    "ShadingOptions",
    "ReflectanceWeights",
    "ReflectanceOptions",
    "REPLACEMENTS",
    "deprecated",
    "module_getattr",
    "shading_arguments",
    "reflectance_arguments",
    "cache_in_options",
]

#: each deprecated name -> what replaces it
REPLACEMENTS = {
    "ShadingWeights": "torchiid.params.ShadingParameters (lambda_* and use_*; .weights())",
    "ShadingOptions": "torchiid.params.ShadingParameters",
    "ReflectanceWeights": "torchiid.params.ReflectanceParameters (gamma_* and use_*; .weights())",
    "ReflectanceOptions": "torchiid.params.ReflectanceParameters",
}


def deprecated(old: str, new: str, stacklevel: int = 3) -> None:
    """Warn that ``old`` is deprecated and ``new`` replaces it."""
    warnings.warn(f"{old} is deprecated; use {new}", DeprecationWarning, stacklevel=stacklevel)


def module_getattr(module: str, name: str) -> Any:
    """A deprecated class read from ``module`` (a warning), or ``AttributeError``."""
    if name not in REPLACEMENTS:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    deprecated(f"{module}.{name}", REPLACEMENTS[name], stacklevel=4)
    return globals()[name]


def _check_tau(tau: float) -> None:
    if not tau > 0:
        raise ParameterError(f"the schedule's tau must be > 0, got {tau}")


_C = TypeVar("_C")
_W = TypeVar("_W", bound="_Weights")
_O = TypeVar("_O", bound="_Options[Any]")
_G = TypeVar("_G", ShadingParameters, ReflectanceParameters)


class _Weights:
    """What both weight classes share: the checks, the τ schedule and the dict form."""

    #: field -> its key in the group's ``weights()``; ``active`` reads these fields
    _KEYS: ClassVar[dict[str, str]]
    #: the fields multiplied by τ after each alternation; the others are divided by it
    _GROWING: ClassVar[tuple[str, ...]]

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not value >= 0:
                raise ParameterError(f"{type(self).__name__}.{f.name} must be >= 0, got {value}")

    @property
    def active(self) -> bool:
        """Whether any prior is on."""
        return any(getattr(self, name) > 0 for name in self._KEYS)

    def step(self: _W, tau: float) -> _W:
        """The next alternation's weights (§3.4): the growing ones ``× τ``, the others ``/ τ``."""
        _check_tau(tau)
        values = dataclasses.asdict(self)
        grown = {k: v * tau if k in self._GROWING else v / tau for k, v in values.items()}
        return type(self)(**grown)

    def as_dict(self) -> dict[str, float]:
        """The weights as the group's ``weights()`` gives them."""
        return {key: getattr(self, name) for name, key in self._KEYS.items()}


@dataclass(frozen=True)
class ShadingWeights(_Weights):
    """Deprecated: the weights of the shading priors (Eq. 1); 0 switches a prior off.

    ``step``: global and mid-level ``× τ``, local ``/ τ``.
    """

    lambda_c: float = 0.02
    lambda_p: float = 0.02
    lambda_m: float = 0.02
    lambda_l: float = 2.0
    lambda_s: float = 0.0

    _KEYS = {
        "lambda_c": "S_c",
        "lambda_p": "S_p",
        "lambda_m": "S_m",
        "lambda_l": "S_l",
        "lambda_s": "S_s",
    }
    _GROWING = ("lambda_c", "lambda_p", "lambda_m")


@dataclass(frozen=True)
class ReflectanceWeights(_Weights):
    """Deprecated: the weights of the reflectance energy (Eq. 12); 0 switches a prior off.

    ``active``: whether any sparsity prior is on; ``step``: mid-level, global, data ``× τ``,
    local ``/ τ``.
    """

    gamma_l: float = 20.0
    gamma_m: float = 20.0
    gamma_g: float = 2.0
    gamma_a: float = 1.0

    _KEYS = {"gamma_l": "A", "gamma_m": "B", "gamma_g": "C"}
    _GROWING = ("gamma_m", "gamma_g", "gamma_a")


class _Options(Generic[_G]):
    """What both option classes share.

    The group's checks, the conversions to and from the group, and the tables by which
    :func:`_stage_arguments` reads an old stage call that takes them.
    """

    #: the group these options convert to, and the ``Parameters`` attribute that holds it
    _GROUP: ClassVar[type[ShadingParameters] | type[ReflectanceParameters]]
    _ATTRIBUTE: ClassVar[str]
    #: the weights these options go with in the old stage calls
    _WEIGHTS: ClassVar[type[_Weights]]
    #: the weights' fields the group holds: weights of no prior, so not in ``as_dict()``
    _CARRIED: ClassVar[tuple[str, ...]]
    #: option -> the group's field, where the names differ
    _NAMES: ClassVar[dict[str, str]]
    #: the options that are not the group's but settings of the stage call -> the call's keyword
    _SETTINGS: ClassVar[dict[str, str]]

    def __post_init__(self) -> None:
        self.to_parameters()  # the group's checks

    def replace(self: _O, **changes: object) -> _O:
        """A copy with some options changed."""
        return dataclasses.replace(self, **changes)

    def to_parameters(self) -> _G:
        """The same settings as the stage's parameter group, without the stage call's settings.

        ``ShadingOptions`` give a :class:`ShadingParameters` (without ``seed`` and ``warn``),
        ``ReflectanceOptions`` a :class:`ReflectanceParameters` (without
        ``merge_stencil_terms`` and ``track_objective``).
        """
        values = dataclasses.asdict(self)
        kept = {k: v for k, v in values.items() if k not in self._SETTINGS}
        return cast(_G, self._GROUP(**{self._NAMES.get(k, k): v for k, v in kept.items()}))

    @classmethod
    def _of(cls: type[_O], group: object, **settings: object) -> _O:
        names = {f.name for f in dataclasses.fields(cls)}
        back = {v: k for k, v in cls._NAMES.items()}
        values = {back.get(k, k): v for k, v in dataclasses.asdict(group).items()}
        return cls(**{k: v for k, v in values.items() if k in names}, **settings)


@dataclass(frozen=True)
class ShadingOptions(_Options[ShadingParameters]):
    """Deprecated: the constants of the shading priors and the settings of their PCG solve."""

    t_c: float = 1e-4
    t_b: float = 0.05
    t_i: float = 0.0
    t_e: float = 0.0
    t_d: float = 0.0
    t_h: float = 0.0
    t_m: float = 0.05
    matting_eps: float = 1e-5
    dark_eps: float = 1e-4
    dark_level: float = 0.0
    clip_level: float = 0.0
    base_sigma: float = 1.0
    base_mix: float = 1.0
    lle_k: int = 10
    lle_reg: float = 1e-3
    lle_neighbours: str = "knn"
    seed: int = 0
    anchor: float = 1e-8
    tol: float = 1e-4
    max_iter: int = 300
    warm_max_iter: int = 0
    levels: int = 5
    warn: bool = True
    preconditioner: str = "jacobi"

    _GROUP = ShadingParameters
    _ATTRIBUTE = "shading"
    _WEIGHTS = ShadingWeights
    _CARRIED = ()
    _NAMES = {
        "tol": "cg_tol",
        "max_iter": "cg_max_iter",
        "warm_max_iter": "warm_cg_max_iter",
        "levels": "coarse_levels",
        "preconditioner": "shading_preconditioner",
    }
    _SETTINGS = {"seed": "seed", "warn": "warn"}

    @classmethod
    def from_parameters(cls, group: ShadingParameters, seed: int, warn: bool) -> ShadingOptions:
        """The options of ``group``."""
        return cls._of(group, seed=seed, warn=warn)


@dataclass(frozen=True)
class ReflectanceOptions(_Options[ReflectanceParameters]):
    """Deprecated: the constants of the reflectance priors and their Split-Bregman settings."""

    theta: float = 40.0
    value_scale: float = 255.0
    t: float = 0.05
    t_g: float = 0.0
    window: int = 11
    colour_weights: str = "bi"
    luminance_weight: float | None = None
    tol: float = 1e-3
    max_outer: int = 3
    cg_tol: float = 1e-3
    cg_max_iter: int = 5
    merge_stencil_terms: bool = True
    warm_state: bool = False
    track_objective: bool = True
    eps: float = 1e-4
    gap_tol: float = 0.0
    theta_floor: float = 1.0

    _GROUP = ReflectanceParameters
    _ATTRIBUTE = "reflectance"
    _WEIGHTS = ReflectanceWeights
    _CARRIED = ("gamma_a",)
    _NAMES = {
        "tol": "bregman_tol",
        "max_outer": "bregman_iter",
        "cg_tol": "bregman_cg_tol",
        "cg_max_iter": "bregman_cg_iter",
        "warm_state": "bregman_warm_state",
        "gap_tol": "bregman_gap_tol",
        "theta_floor": "bregman_theta_floor",
        "eps": "shading_floor",
    }
    _SETTINGS = {"merge_stencil_terms": "merge", "track_objective": "track_objective"}

    @classmethod
    def from_parameters(
        cls, group: ReflectanceParameters, track_objective: bool
    ) -> ReflectanceOptions:
        """The options of ``group``."""
        return cls._of(group, track_objective=track_objective)


def _stage_arguments(
    function: str, first: object, options: object, kind: type[_Options[Any]]
) -> tuple[Any, dict[str, float], dict[str, Any]]:
    """``(group, weights, settings)`` of a call of the stage function ``function``.

    The new form is ``(group, None)``; the old one ``(weights, options)``, with options of
    ``kind``, warns (at the stage function's caller) and gives the options that are settings
    of the call in ``settings``, under the call's keywords.
    """
    group_name = f"torchiid.params.{kind._GROUP.__name__}"
    attribute = f"params.{kind._ATTRIBUTE}"
    if isinstance(first, kind._GROUP) and options is None:
        return first, first.weights(), {}
    if isinstance(first, kind._WEIGHTS) and isinstance(options, kind):
        deprecated(
            f"{function}(problem, {kind._WEIGHTS.__name__}, {kind.__name__})",
            f"{function}(problem, {attribute}) with a {group_name}",
            stacklevel=5,
        )
        carried = {name: getattr(first, name) for name in kind._CARRIED}
        settings = {key: getattr(options, name) for name, key in kind._SETTINGS.items()}
        return options.to_parameters().replace(**carried), first.as_dict(), settings
    raise ParameterError(
        f"{function} takes a {group_name} ({attribute}), got {type(first).__name__}"
    )


def shading_arguments(
    function: str, shading: object, options: object
) -> tuple[ShadingParameters, dict[str, float], dict[str, Any]]:
    """``(group, weights, settings)`` of a shading stage call, old form or new.

    The new form is ``(ShadingParameters, None)``; the old one ``(ShadingWeights,
    ShadingOptions)`` warns and gives its ``seed`` and ``warn`` in ``settings``.
    """
    return _stage_arguments(function, shading, options, ShadingOptions)


def reflectance_arguments(
    function: str, reflectance: object, options: object
) -> tuple[ReflectanceParameters, dict[str, float], dict[str, Any]]:
    """``(group, weights, settings)`` of a reflectance stage call, old form or new.

    The new form is ``(ReflectanceParameters, None)``; the old one ``(ReflectanceWeights,
    ReflectanceOptions)`` warns and gives ``merge`` and ``track_objective`` in ``settings``.
    """
    return _stage_arguments(function, reflectance, options, ReflectanceOptions)


def cache_in_options(options: object, cache: _C | None, kind: type[_C]) -> tuple[object, _C | None]:
    """``(options, cache)`` of a build call whose third argument may be its cache.

    The new form passes the cache where the old one passed its options: ``(problem, group,
    cache)``; a ``kind`` there, with no ``cache`` given, is the cache.
    """
    if isinstance(options, kind) and cache is None:
        return None, options
    return options, cache
