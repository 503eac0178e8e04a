"""Loading a script of ``tools/`` as a module, and putting things back afterwards."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

TOOLS = Path(__file__).resolve().parents[2] / "tools"


@pytest.fixture(scope="module")
def load_tool():
    """``load_tool(name)``: ``tools/<name>.py`` as module ``name``, registered in ``sys.modules``.

    The tools put ``tools/`` on ``sys.path`` and import each other (``bench_bell``); the
    module's teardown restores the path and forgets every module loaded from ``tools/``.
    """
    path, before = list(sys.path), set(sys.modules)

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        return module

    yield load
    for name in set(sys.modules) - before:
        if Path(getattr(sys.modules[name], "__file__", None) or "/").parent == TOOLS:
            del sys.modules[name]
    sys.path[:] = path
