"""Parameters of the method: one frozen dataclass made of the stages' groups, with presets.

:class:`Parameters` holds every number and switch of the method, in groups that are the
objects the stages take (``params.shading`` for Stage 1, ``params.reflectance`` for Stage 2,
``params.features`` for Stage 0, ``params.output`` for the layers), and the schedule of the
alternations (``iterations``, ``tau``). ``Parameters()`` is what :func:`torchiid.decompose`
does by default (the ``default`` preset); ``Parameters.preset("paper")`` gives the paper's
values with the most thorough solver settings (§3.4 and Table 1).

Every parameter also has a flat name, the same in every group (``lambda_l`` is
``params.shading.lambda_l``): ``Parameters(lambda_l=1.0)``, :meth:`Parameters.replace`,
:data:`PRESETS` and the parameter files (:meth:`Parameters.to_json`,
:meth:`Parameters.from_json`) use it.
"""

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

from torchiid.core.exceptions import ParameterError
from torchiid.params import files
from torchiid.params.fields import check_fields, param
from torchiid.params.groups import FeatureParameters, OutputParameters
from torchiid.params.presets import ALL_ON, PRESETS, VARIANTS
from torchiid.params.reflectance import ReflectanceParameters
from torchiid.params.shading import ShadingParameters

__all__ = ["Parameters", "GROUPS", "FLAT_NAMES"]

#: the groups of :class:`Parameters`: attribute -> class
GROUPS: dict[str, type] = {
    "features": FeatureParameters,
    "shading": ShadingParameters,
    "reflectance": ReflectanceParameters,
    "output": OutputParameters,
}
#: every flat name of a grouped parameter -> its group
FLAT_NAMES: dict[str, str] = {
    f.name: group for group, cls in GROUPS.items() for f in dataclasses.fields(cls)
}


def _group(doc: str, cls: type) -> Any:
    return dataclasses.field(default_factory=cls, metadata={"doc": doc})


@dataclasses.dataclass(frozen=True, init=False)
class Parameters:
    """Every parameter of the decomposition.

    Four groups and the schedule. Each leaf field's metadata holds its meaning (``"doc"``), the
    paper's value (``"paper"``), its valid range (``"valid"``) and, for tuned values, why
    the default differs from the paper (``"why"``); see :mod:`torchiid.params.fields`.

    Construction takes the groups, the schedule fields or flat names, which change the
    corresponding group field: ``Parameters(lambda_l=1.0)`` equals
    ``Parameters(shading=ShadingParameters(lambda_l=1.0))``. A grouped parameter is read
    from its group (``params.shading.lambda_l``); its flat name as an attribute raises an
    ``AttributeError`` naming the group.

    Raises:
        ParameterError: an unknown name, a value of the wrong type or out of range (the
            message names the parameter and the value).
    """

    features: FeatureParameters = _group(
        "Stage 0: the semantic features (patches, proposals, segments)", FeatureParameters
    )
    shading: ShadingParameters = _group("Stage 1: the L2 shading solve (Eq. 1)", ShadingParameters)
    reflectance: ReflectanceParameters = _group(
        "Stage 2: the L1 reflectance solve (Eq. 12)", ReflectanceParameters
    )
    output: OutputParameters = _group(
        "the working resolution and the full-resolution layers", OutputParameters
    )
    iterations: int = param(5, "alternations k of Stage 1 and Stage 2", paper=5, valid="> 0")
    tau: float = param(
        1.2,
        "after each alternation the mid-level, global and data weights are multiplied by τ "
        "and the local weights divided by it (§3.4)",
        paper=1.2,
        valid="> 0",
    )
    coarse_scale: float = param(
        0.5,
        "the alternations before the last run at this fraction of the working resolution's "
        "sides; the last one, at the working resolution, starts from their result "
        "(1: every alternation at the working resolution)",
        paper=1.0,
        valid="in (0, 1]",
        why="0.5: a solver setting for speed, a quarter less time per photo; MIT-Berkeley "
        "0.0206 against 0.0204 (Method: Coarse-to-fine alternations)",
    )
    seed: int = param(
        0,
        "seed of every random choice (the ranking of the proposals, random LLE neighbours)",
        valid="any integer",
    )
    converge: bool = param(
        False,
        "solve every stage to its tolerance: a solve that stops at its cap (then a safety "
        "cap) raises a ConvergenceWarning (false: the caps are part of the preset)",
        valid="true or false",
    )

    def __init__(self, **values: Any) -> None:
        _check_names(values)
        for name, cls in GROUPS.items():
            group = values.pop(name, None)
            if group is None:
                group = cls()
            elif not isinstance(group, cls):
                raise ParameterError(
                    f"parameter {name} must be a {cls.__name__}, got {type(group).__name__}"
                )
            flat = {k: values.pop(k) for k in list(values) if FLAT_NAMES.get(k) == name}
            object.__setattr__(self, name, group.replace(**flat) if flat else group)
        for f in dataclasses.fields(self):
            if f.name not in GROUPS:
                object.__setattr__(self, f.name, values.pop(f.name, f.default))
        check_fields(self)
        if not (self.shading.stage1 or self.reflectance.stage2):
            raise ParameterError("at least one of stage1 and stage2 must be on")
        side, patch = self.output.max_side, self.features.patch_size
        if 0 < side < patch:  # every image would be refused at its working resolution
            raise ParameterError(
                f"parameter max_side must be 0 (no resizing) or at least patch_size ({patch}), "
                f"got {side}"
            )

    def __getattr__(self, name: str) -> Any:
        # only called when the normal lookup fails: a grouped parameter's flat name is not an
        # attribute, and the error names its group
        group = FLAT_NAMES.get(name)
        where = f"; read params.{group}.{name}" if group is not None else ""
        raise AttributeError(f"'Parameters' object has no attribute {name!r}{where}")

    # ------------------------------------------------------------------ construction
    @classmethod
    def preset(cls, name: str) -> "Parameters":
        """A named parameter set: ``default``, ``print``, ``texture``, ``paper``, ``converged``.

        The names are the keys of :data:`PRESETS`.
        """
        if name not in PRESETS:
            raise ParameterError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        return cls(**PRESETS[name])

    def replace(self, **changes: Any) -> "Parameters":
        """A copy with some parameters changed, by flat name or group (unknown names rejected)."""
        _check_names(changes)
        current = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return type(self)(**{**current, **changes})

    def variant(self, name: str) -> "Parameters":
        """The paper's ablation variant (``v1``–``v7``, Table 3) or baseline (``baseline1``–3).

        ``v1``: S_l with all reflectance priors; ``v2``: + S_g; ``v3``: + S_m instead of S_g;
        ``v4``: all shading priors, R_l only; ``v5``: R_l + R_g; ``v6``: R_l + R_m; ``v7``: all.
        ``baseline1``: shading smoothness only (Stage 1, no Stage 2); ``baseline2``:
        reflectance sparsity only (Stage 2 on ρ = I); ``baseline3``: flattening as reflectance
        (Stage 2 local term only, on ρ = I).

        Every switch is set (the others of the variant are on), so
        ``p.variant("v4").variant("v7") == p.variant("v7")``.
        """
        if name not in VARIANTS:
            raise ParameterError(f"unknown variant {name!r}; choose one of {', '.join(VARIANTS)}")
        return self.replace(**{**ALL_ON, **VARIANTS[name]})

    # ------------------------------------------------------------------ the schedule
    def alternation(self, k: int) -> tuple[ShadingParameters, ReflectanceParameters]:
        """The two stages' groups at alternation ``k`` (1-based) of the §3.4 schedule.

        Each weight has been stepped ``k - 1`` times by ``tau`` (:meth:`ParameterGroup.step
        <torchiid.params.fields.ParameterGroup.step>`: mid-level, global and data weights
        ``× τ``, local ones ``÷ τ``); every other field is as configured.
        """
        shading, reflectance = self.shading, self.reflectance
        for _ in range(k - 1):
            shading, reflectance = shading.step(self.tau), reflectance.step(self.tau)
        return shading, reflectance

    # ------------------------------------------------------------------ the flat form
    def to_dict(self) -> dict[str, Any]:
        """Every parameter by its flat name (the form of a parameter file, without version)."""
        flat: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name in GROUPS:
                flat.update(dataclasses.asdict(value))
            else:
                flat[f.name] = value
        return flat

    @classmethod
    def from_dict(cls, data: dict[str, Any], base: "Parameters | None" = None) -> "Parameters":
        """Build from a flat mapping, as :meth:`from_json` reads a file's object.

        Names it does not give keep the values of ``base`` (default ``Parameters()``), or
        those the version that wrote it ran (:mod:`torchiid.params.files`); unknown names
        raise :class:`ParameterError` naming the key.
        """
        if not isinstance(data, dict):
            raise ParameterError(f"parameters must be a JSON object, got {type(data).__name__}")
        return _read(cls, data, base, "parameters")

    @classmethod
    def from_json(cls, path: Any, base: "Parameters | None" = None) -> "Parameters":
        """Read a parameter file; keys it does not name keep the values of ``base`` (or defaults).

        A file written by an earlier version replays what that version ran for the parameters
        added since (:data:`~torchiid.params.files.ADDED_SINCE`): with ``torchiid_version``,
        those it lacks that a later version added; without one, when it names every parameter
        except some of those (a complete record, as the CLI's ``-params.json``). A warning
        names them. A file of a few overrides keeps ``base``'s other values.

        Raises:
            ParameterError: the file is missing or unreadable, not UTF-8 text, not a JSON
                object, or holds an unknown key, a value of the wrong type or a value out of
                range (also NaN or infinity); the one-line message names the file.
        """
        path = Path(path)
        data = files.read_json_object(path)
        try:
            return _read(cls, data, base, str(path))
        except ParameterError as exc:
            raise ParameterError(f"{path}: {exc}") from None
        except (TypeError, ValueError, OverflowError) as exc:  # e.g. an integer beyond a float
            raise ParameterError(f"{path}: invalid parameter value ({exc})") from None

    def to_json(self, path: Any = None) -> str:
        """The parameters as JSON text, flat, with the version that wrote them.

        Written to ``path`` (atomically) when given.
        """
        data = {files.VERSION_KEY: _package_version(), **dict(sorted(self.to_dict().items()))}
        text = json.dumps(data, indent=2) + "\n"
        if path is not None:
            files.write_text(path, text)
        return text


def _package_version() -> str:
    """``torchiid.__version__``.

    Read from the imported package (a package is imported before any of its modules runs):
    ``import torchiid`` here would tie this module to the root, which imports it.
    """
    return sys.modules[__name__.partition(".")[0]].__version__


def _check_names(values: dict[str, Any]) -> None:
    known = {f.name for f in dataclasses.fields(Parameters)}
    for key in values:
        if key not in known and key not in FLAT_NAMES:
            raise ParameterError(f"Invalid parameter: {key}")


def _read(cls: type, data: dict[str, Any], base: Parameters | None, where: str) -> Parameters:
    """Parameters from a flat mapping over ``base``, replaying what an older version ran."""
    data = dict(data)
    version = data.pop(files.VERSION_KEY, None)
    if version is not None:
        files.version_key(version)  # a readable version, or a ParameterError
    _check_names(data)
    names = set(FLAT_NAMES) | {f.name for f in dataclasses.fields(cls) if f.name not in GROUPS}
    replayed = files.added_after(version, data, names)
    files.log_replayed(where, version, replayed)
    start = base.to_dict() if base is not None else {}
    return cls(**{**start, **replayed, **data})
