"""Running a step of the method as it is inside a ``torch.compile`` graph."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import torch

__all__ = ["eager_under_compile"]

F = TypeVar("F", bound=Callable[..., Any])


def eager_under_compile(run: F) -> F:
    """``run``, or, while ``torch.compile`` traces the caller, ``run`` left out of its graph.

    The method's steps (data-dependent solver loops; NumPy, numba and onnxruntime calls; sums
    over stencil offsets) gain nothing from compilation: dynamo splits them into many graphs
    that inductor takes minutes to compile. Left out, they run as they do uncompiled while the
    model around them compiles, and gradients cross the boundary. Decided at each call rather
    than by marking the functions once: ``torch.compiler.disable`` imports the compiler's
    machinery, over a second and 80 MB for every process that loads torchiid.
    """
    if torch.compiler.is_compiling():
        disabled: F = torch.compiler.disable(run)  # type: ignore[no-untyped-call]
        return disabled
    return run
