"""Saying so while the CPU kernels compile, the first time they run in a Python environment.

numba compiles torchiid's kernels on their first use and keeps the machine code in its cache
on disk, so that every later process loads it in a fraction of a second. The first
compilation takes up to a minute on 2 cores, and a run shows no progress meanwhile. numba
broadcasts a ``"numba:compile"`` event (its documented event API, :mod:`numba.core.event`)
only for a function that is not in its cache: a load from the cache broadcasts none. A
listener on that event therefore tells exactly when a user is waiting for the compiler, with
no guess about where the cache lives or whether it is current.

:func:`watch_compilation` registers the listener; :mod:`torchiid.priors.kernel_runtime` calls
it where it imports numba, so a process that never uses the kernels never imports numba for
it. :func:`notify_first_compile` is what a command or the app wraps a run in. This module
imports neither torch nor numba.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["COMPILING", "notify_first_compile", "watch_compilation"]

#: what the command line and the app say while the kernels compile
COMPILING = (
    "compiling the CPU kernels, once for this Python environment (up to a minute; "
    "later runs load them from numba's cache)"
)

logger = logging.getLogger("torchiid")

_lock = threading.Lock()
_waiting: list[_Once] = []
_watching = False


class _Once:
    """A callback that runs at most once."""

    def __init__(self, callback: Callable[[], None]) -> None:
        self.callback = callback
        self.done = False

    def __call__(self) -> None:
        with _lock:
            if self.done:
                return
            self.done = True
        try:
            self.callback()
        except Exception:  # noqa: BLE001 - a note must not fail the compilation it announces
            logger.debug("the note of the kernels' compilation failed", exc_info=True)


@contextmanager
def notify_first_compile(callback: Callable[[], None]) -> Iterator[None]:
    """Call ``callback()`` once if a torchiid kernel compiles while the block runs.

    A kernel compiles when numba's cache has no machine code for it (a fresh environment, a
    new torchiid or numba version, a cleared cache); loading it from the cache does not call
    ``callback``. The call comes from the thread that compiles, before the compilation; an
    exception it raises is logged (at debug level) and does not stop the compilation.

    Example:
        >>> from torchiid.core.first_compile import notify_first_compile
        >>> with notify_first_compile(lambda: print("compiling the kernels...")):
        ...     pass  # e.g. torchiid.decompose(image)
    """
    once = _Once(callback)
    with _lock:
        _waiting.append(once)
    try:
        yield
    finally:
        with _lock:
            _waiting.remove(once)


def watch_compilation() -> None:
    """Listen for numba compiling a torchiid function (once per process; imports numba)."""
    global _watching
    with _lock:
        if _watching:
            return
        _watching = True
    from numba.core import event

    class _Listener(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            dispatcher = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
            module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
            if module.startswith("torchiid."):  # another library's functions are its own
                with _lock:
                    waiting = list(_waiting)
                for once in waiting:
                    once()

        def on_end(self, ev: event.Event) -> None:
            pass

    event.register("numba:compile", _Listener())
