"""Typed exceptions raised by torchiid.

Every error a user can cause (bad file, bad tensor, bad parameter) is a subclass of
:class:`TorchiidError`, so a caller can catch one type; the CLI turns it into a one-line
message and a non-zero exit status.
"""

from __future__ import annotations

__all__ = [
    "caused_by_interrupt",
    "TorchiidError",
    "ImageError",
    "ShapeError",
    "ParameterError",
    "ModelError",
    "MemoryLimitError",
    "ConvergenceWarning",
    "InputWarning",
    "one_line",
    "describe_error",
]


class TorchiidError(ValueError):
    """Base class of every user-facing torchiid error."""


class ImageError(TorchiidError):
    """An image file or tensor cannot be used (unreadable, empty, too small, NaN, ...)."""


class ShapeError(TorchiidError):
    """A tensor has the wrong shape, dtype or device for the operation."""


class ParameterError(TorchiidError):
    """A parameter value or parameter file is invalid."""


class ModelError(TorchiidError):
    """A backbone model (weights or exported ONNX file) is missing or corrupt."""


class MemoryLimitError(TorchiidError):
    """A decomposition would need more memory than the machine (or its container) has left.

    Raised before the work starts, so nothing is half done; the message says how much would be
    needed, how much is available and how to need less.
    """


class ConvergenceWarning(UserWarning):
    """An iterative solver stopped before reaching its tolerance."""


class InputWarning(UserWarning):
    """An input was usable only after a change that the user should know of.

    For example, a float file's few negative values set to 0
    (:func:`~torchiid.io.validate.clip_negatives`).
    """


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (newlines included) made one space."""
    return " ".join(text.split())


def describe_error(exc: BaseException) -> str:
    """A one-line description of ``exc`` for a user (without the file it concerns).

    torchiid's own errors say what is wrong in their message; a file-system error says which
    file and why; out-of-memory and torch's runtime errors keep their type; anything else is
    an internal error, and the user is told how to get the traceback.
    """
    if isinstance(exc, TorchiidError):
        return one_line(str(exc))
    if isinstance(exc, OSError):
        where = f" {exc.filename}" if exc.filename else ""
        return f"cannot access{where} ({exc.strerror or one_line(str(exc))})"
    if isinstance(exc, (RuntimeError, MemoryError)):
        return f"{type(exc).__name__}: {one_line(str(exc))}"
    return (
        f"internal error ({type(exc).__name__}: {one_line(str(exc))}); "
        "rerun with --verbose for the traceback"
    )


def caused_by_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` came from a ``KeyboardInterrupt`` (anywhere in its cause chain).

    Ctrl-C inside a numba kernel reaches Python as ``SystemError: ... returned a result with
    an exception set`` whose cause is the interrupt: that is an interruption, not a failure.
    """
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False
