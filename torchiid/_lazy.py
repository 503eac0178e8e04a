"""Packages whose public names load on first use (PEP 562).

A package that re-exports names from modules that import torch would load torch as soon as
any of its modules is imported (Python runs the package's ``__init__`` first). Those whose
light modules a quick path needs (the command line's parsers, a rerun that finds every
image done) declare their names with :func:`lazy_names` instead, and list them under
``if TYPE_CHECKING:`` for static tools.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_names"]


def lazy_names(
    package: str, sources: Mapping[str, str], namespace: dict[str, Any]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """A package's ``__getattr__`` and ``__dir__`` for names defined in its modules.

    A submodule (``torchiid.io.layers``) is imported on first access too, as if the package
    had imported it.

    Args:
        package: the package's ``__name__``.
        sources: public name -> the module it is defined in.
        namespace: the package's ``globals()``: a loaded name is kept there, so later
            lookups do not come back.

    Example:
        >>> g = {}
        >>> get, _ = lazy_names("pkg", {"dumps": "json"}, g)
        >>> get("dumps")({"a": 1}), "dumps" in g
        ('{"a": 1}', True)
    """

    def __getattr__(name: str) -> Any:
        if name in sources:
            value = getattr(importlib.import_module(sources[name]), name)
        elif not name.startswith("_") and importlib.util.find_spec(f"{package}.{name}"):
            # a submodule, imported on first access as if the package had imported it
            value = importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(sources))

    return __getattr__, __dir__
