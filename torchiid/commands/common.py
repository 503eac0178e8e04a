"""What every command shares: the run options, the parameter options and the quiet console.

Nothing here imports torch (or anything heavy) at module level: the parsers are built for
``torchiid --help`` too, which must start at once.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    from torchiid.params import Parameters

__all__ = [
    "DEVICES",
    "MEMORY_LIMIT_VARIABLE",
    "THREAD_VARIABLES",
    "add_overwrite_and_linear",
    "add_parameter_options",
    "params_from_args",
    "run_environment",
    "run_options",
    "say",
    "verbosity_options",
]

DEVICES = ("auto", "cpu", "cuda")

#: set to ``--threads`` before torch loads, so its OpenMP pool starts with that many threads
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")

_N = TypeVar("_N", int, float)


def _add_verbosity(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: given after the command they set the value; absent, they keep the global
    # option's (``torchiid -v decompose ...`` and ``torchiid decompose -v ...`` both work)
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=argparse.SUPPRESS,
        help="print only errors (no progress bar, notes or summaries)",
    )
    group.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        default=argparse.SUPPRESS,
        help="print details: per-item lines, solver reports, tracebacks of internal errors",
    )


def verbosity_options() -> argparse.ArgumentParser:
    """A parent parser with ``-q/--quiet`` and ``-v/--verbose``."""
    p = argparse.ArgumentParser(add_help=False)
    _add_verbosity(p)
    return p


def _number(text: str, kind: type[_N], what: str) -> _N:
    """``text`` read as a ``kind``; otherwise argparse's error "not ``what``"."""
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not {what}: {text!r}") from None


def finite_float(text: str) -> float:
    """An option's number; argparse refuses NaN and infinities (status 2) before any work."""
    value = _number(text, float, "a number")
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"not a finite number: {text!r}")
    return value


def _threads(text: str) -> int:
    value = _number(text, int, "a whole number")
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def run_options() -> argparse.ArgumentParser:
    """A parent parser with the options of every command that runs long.

    ``--no-progress``, ``--device``, ``--threads N``, ``--memory-limit GB``, ``-q/--quiet``,
    ``-v/--verbose``.
    """
    p = argparse.ArgumentParser(add_help=False)
    group = p.add_argument_group("run options")
    group.add_argument("--no-progress", action="store_true", help="no progress bar")
    group.add_argument(
        "--device",
        default="auto",
        choices=DEVICES,
        help="where to run (auto: CUDA when available)",
    )
    group.add_argument(
        "--threads",
        type=_threads,
        metavar="N",
        help="CPU threads (torch and OpenMP; default: every core)",
    )
    group.add_argument(
        "--memory-limit",
        type=_gigabytes,
        metavar="GB",
        help="refuse a photo whose decomposition would take more than GB of memory (default: "
        "what the machine has left; also the environment variable TORCHIID_MEMORY_LIMIT)",
    )
    _add_verbosity(group)
    return p


def _gigabytes(text: str) -> float:
    value = _number(text, float, "a number of GB")
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number of GB > 0, got {text}")
    return value


def add_parameter_options(p: argparse.ArgumentParser) -> None:
    """The options that choose the method's parameters (``decompose``, ``edit``, ``eval``...)."""
    p.add_argument(
        "--preset",
        default="default",
        help=(
            "parameter preset: default, print (photos of printed matter: documents, "
            "labels), texture (densely textured surfaces: tiles, wood, fabric), paper or "
            "converged (every solve to tolerance)"
        ),
    )
    p.add_argument("--params", type=Path, help="JSON file of parameters (over the preset)")
    p.add_argument("--variant", help="ablation variant v1..v7 or baseline1..baseline3")
    from torchiid.params import PRESETS, Parameters

    presets = [Parameters.preset(name) for name in PRESETS]
    ks = sorted({p.iterations for p in presets})
    sides = sorted({p.output.max_side for p in presets})
    p.add_argument(
        "--iterations",
        type=int,
        metavar="K",
        help=f"alternations k (default: the preset's, {' or '.join(map(str, ks))})",
    )
    p.add_argument(
        "--max-side",
        type=int,
        metavar="PX",
        help="working resolution: the longer side in px (default: the preset's, "
        f"{' or '.join(map(str, sides))}; 0: the full resolution)",
    )


def add_overwrite_and_linear(p: argparse.ArgumentParser, files: str = "input") -> None:
    """``--overwrite`` and ``--linear`` (what 8/16-bit ``files`` files hold), in that order."""
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument(
        "--linear",
        action="store_true",
        help=f"8/16-bit {files} files hold linear values (default: sRGB-encoded)",
    )


def params_from_args(args: argparse.Namespace) -> Parameters:
    """Parameters from --preset, --params, --variant, --iterations and --max-side."""
    from torchiid.core.exceptions import ParameterError
    from torchiid.params import Parameters

    params = Parameters.preset(args.preset)
    if args.params is not None:
        params = Parameters.from_json(args.params, base=params)
    if args.variant:
        params = params.variant(args.variant)
    if args.iterations is not None:
        if args.iterations < 1:
            raise ParameterError(f"--iterations must be >= 1, got {args.iterations}")
        params = params.replace(iterations=args.iterations)
    if args.max_side is not None:
        if args.max_side < 0:
            raise ParameterError(
                f"--max-side must be >= 0 (0: the full resolution), got {args.max_side}"
            )
        params = params.replace(max_side=args.max_side)
    return params


def progress_bars(args: argparse.Namespace) -> bool:
    """Whether to draw progress bars: not ``--no-progress`` or ``-q``, and stderr a terminal.

    A bar redraws its line with carriage returns; in a log file or a pipe those pile up on
    one line and the messages land among them, so there a run writes lines instead
    (:mod:`torchiid.core.progress`).
    """
    from torchiid.core.progress import stderr_is_terminal

    return not getattr(args, "no_progress", False) and stderr_is_terminal()


def say(args: argparse.Namespace, message: str) -> None:
    """Print a note or a summary line to stderr, unless ``-q``."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr)


#: the memory cap of every decomposition (GB), read by :func:`torchiid.core.memory.memory_limit`;
#: an environment variable, so that worker processes inherit it
MEMORY_LIMIT_VARIABLE = "TORCHIID_MEMORY_LIMIT"


def run_environment(threads: int | None, memory_gb: float | None) -> dict[str, str | None]:
    """Set :data:`THREAD_VARIABLES` to ``threads`` and the memory cap; returns previous values."""
    previous = {name: os.environ.get(name) for name in (*THREAD_VARIABLES, MEMORY_LIMIT_VARIABLE)}
    if threads is not None:
        for name in THREAD_VARIABLES:
            os.environ[name] = str(threads)
    if memory_gb is not None:
        os.environ[MEMORY_LIMIT_VARIABLE] = repr(memory_gb)
    return previous
