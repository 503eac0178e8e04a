"""Parameter files: the flat JSON form, and the replay of files written by earlier versions.

A parameter file is one JSON object of flat parameter names (``{"lambda_l": 2.0, ...}``) and,
when torchiid wrote it, ``"torchiid_version"``. Reading one starts from a base parameter set
(the preset) and takes the file's values; a parameter the file does not name keeps the base's
value, unless the file comes from a version that did not have it yet: then it takes the value
that version ran (:data:`ADDED_SINCE`), so an old file replays what it recorded.
"""

import json
import logging
import os
import re
from pathlib import Path
from typing import Any

from torchiid.core.exceptions import ParameterError

__all__ = ["ADDED_SINCE", "VERSION_KEY", "added_after", "read_json_object", "write_text"]

logger = logging.getLogger("torchiid.params")

#: the key of a parameter file that names the torchiid version that wrote it
VERSION_KEY = "torchiid_version"

#: Parameters added since the parameter set took its present shape, by the version that added
#: them, with the value that runs what the method did before (a switch off, the paper's
#: choice, or the value the earlier version had built in, as ``t_x_sigma``'s 3 px before
#: 1.1.0). Each new parameter must be added here under its version
#: (``tests/test_params.py`` checks that every parameter is here or in the oldest record).
ADDED_SINCE: dict[str, dict[str, Any]] = {
    "0.5.0": {"shading_preconditioner": "jacobi"},
    "0.8.0": {"t_i": 0.0},
    "0.9.0": {"converge": False, "bregman_warm_state": False, "luminance_weight": None},
    "0.10.0": {"lambda_s": 0.0, "t_e": 0.0, "t_d": 0.0, "t_h": 0.0},
    "0.11.0": {"bregman_gap_tol": 0.0, "bregman_theta_floor": 1.0},
    "0.12.0": {"base_mix": 1.0},
    "1.0.0": {"t_x": 0.0},
    "1.1.0": {"t_x_sigma": 3.0},
    "1.13.0": {"coarse_scale": 1.0},
    "1.16.0": {"t_xc": 0.0},
}


def version_key(version: str) -> tuple[int, ...]:
    """``"0.12.0"`` -> ``(0, 12, 0)``, for numeric comparison (a suffix as ``rc1`` is ignored).

    Raises:
        ParameterError: not a version.
    """
    match = re.match(r"(\d+(?:\.\d+)*)", version) if isinstance(version, str) else None
    if match is None:
        raise ParameterError(f'{VERSION_KEY} must be a version such as "1.0.0", got {version!r}')
    return tuple(int(part) for part in match.group(1).split("."))


def added_after(version: str | None, data: dict[str, Any], names: set[str]) -> dict[str, Any]:
    """The values a file from ``version`` ran for the parameters it lacks that came later.

    With a version: every parameter of :data:`ADDED_SINCE` added in a later version that
    ``data`` does not name. Without one: the file counts as the oldest record if it is
    complete, naming every parameter of ``names`` that is not in :data:`ADDED_SINCE` (a file
    of a few overrides is not a record: ``{}``), and the missing ones of :data:`ADDED_SINCE`
    take their old values.
    """
    if version is not None:
        written = version_key(version)
        return {
            name: value
            for since, added in ADDED_SINCE.items()
            if version_key(since) > written
            for name, value in added.items()
            if name not in data
        }
    later = {name: value for added in ADDED_SINCE.values() for name, value in added.items()}
    missing = names - set(data)
    if not missing or not missing <= later.keys():
        return {}
    return {name: later[name] for name in missing}


def log_replayed(where: str, version: str | None, replayed: dict[str, Any]) -> None:
    """One warning naming the parameters a file from an earlier version replays."""
    if not replayed:
        return
    which = f"torchiid {version}" if version is not None else "it names every parameter but"
    if version is None:
        which += " " + ", ".join(sorted(replayed))
    logger.warning(
        "%s: a parameter file from an earlier torchiid (%s); those it lacks take the values "
        "that version ran: %s (add them to the file to choose others)",
        where,
        which,
        ", ".join(f"{k} {v!r}" for k, v in sorted(replayed.items())),
    )


def read_json_object(path: Path) -> dict[str, Any]:
    """The JSON object of a parameter file.

    Raises:
        ParameterError: the file is missing or unreadable, not UTF-8 text, not JSON (NaN and
            infinity included) or not an object; the one-line message names the file.
    """
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ParameterError(f"{path}: no such parameter file") from None
    except IsADirectoryError:
        raise ParameterError(f"{path}: is a directory, not a parameter file") from None
    except OSError as exc:
        why = exc.strerror or " ".join(str(exc).split())
        raise ParameterError(f"{path}: cannot read the parameter file ({why})") from None
    try:
        text = raw.decode("utf-8-sig")  # a byte-order mark, as some editors write, is fine
    except UnicodeDecodeError as exc:
        raise ParameterError(
            f"{path}: not a UTF-8 text file (byte 0x{raw[exc.start]:02x} at offset "
            f"{exc.start}); save the parameter file as UTF-8 JSON"
        ) from None

    def finite(value: str) -> float:
        number = float(value)
        if number in (float("inf"), float("-inf")):
            raise ValueError(f"{value} is out of range")
        return number

    def reject(name: str) -> None:
        raise ValueError(f"{name} is not a valid value")

    try:
        data = json.loads(text, parse_float=finite, parse_constant=reject)
    except (json.JSONDecodeError, ValueError, RecursionError) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__
        raise ParameterError(f"{path}: not a readable JSON file ({why})") from None
    if not isinstance(data, dict):
        kind = {list: "array", str: "string", bool: "true/false", type(None): "null"}
        raise ParameterError(
            f"{path}: expected a JSON object of parameters ({{...}}), got a JSON "
            f"{kind.get(type(data), 'number')}"
        )
    return data


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a temporary file, then a rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
