"""Progress on stderr: a bar on a terminal, a line now and then in a log file or a pipe.

A bar redraws its line with carriage returns. On a terminal that is one line kept up to date;
in a log file or a pipe the redraws pile up on a single line, with the run's messages among
them. There a long run (an evaluation, a video) writes a plain line at most every
:data:`EVERY` seconds instead: how many items are done, the rate and the time left.
"""

from __future__ import annotations

import sys
import time
from typing import IO, Any

__all__ = ["EVERY", "ProgressLines", "progress", "stderr_is_terminal"]

#: seconds between two lines of :class:`ProgressLines`
EVERY = 30.0


def stderr_is_terminal() -> bool:
    """Whether stderr is a terminal (``False`` for a file, a pipe, a closed stream)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


class ProgressLines:
    """A progress bar's stand-in for a log: a line at most every ``every`` seconds.

    It takes the calls the commands make on their bars: ``update``, ``write`` and ``close``.
    A line reads ``frames: 120 of 400 frames, 2.1 frames/s, 2 min 13 s left`` (without a total,
    the count and the rate alone).

    Args:
        total: how many items, or ``None`` when unknown.
        desc: what is counted, first on the line.
        unit: the items' name, plural with an ``s``.
        every: the least number of seconds between two lines (default :data:`EVERY`).
        file: where the lines go (default stderr).
        initial: items done before (a resumed run); the rate counts those done since.
    """

    def __init__(
        self,
        total: int | None,
        desc: str,
        unit: str,
        every: float | None = None,
        file: IO[str] | None = None,
        initial: int = 0,
    ) -> None:
        self.total, self.desc, self.unit = total, desc, unit
        self.every = EVERY if every is None else every
        self.file = file
        self.n = self.initial = initial
        self.start = self.last = time.monotonic()

    def update(self, n: int = 1) -> None:
        """``n`` more items done; a line if ``every`` seconds have passed since the last."""
        self.n += n
        now = time.monotonic()
        if now - self.last >= self.every:
            self.last = now
            print(self.line(now - self.start), file=self.file or sys.stderr, flush=True)

    def line(self, elapsed: float) -> str:
        """The line for ``elapsed`` seconds since the start."""
        units = f"{self.unit}s"
        text = f"{self.desc}: {self.n}" + (f" of {self.total}" if self.total else "")
        rate = (self.n - self.initial) / elapsed if elapsed > 0 else 0.0
        shown = f"{rate:.0f}" if rate >= 10 else f"{rate:.1f}" if rate >= 1 else f"{rate:.2g}"
        text += f" {units}, {shown} {units}/s"
        if self.total and rate > 0 and self.n < self.total:
            minutes, seconds = divmod(round((self.total - self.n) / rate), 60)
            text += f", {minutes} min {seconds} s left" if minutes else f", {seconds} s left"
        return text

    @staticmethod
    def write(message: str, file: IO[str] | None = None) -> None:
        """A message on its own line, as ``tqdm.write``."""
        print(message, file=file or sys.stderr, flush=True)

    def close(self) -> None:
        """Nothing to clear: the command prints its own summary."""


def progress(
    total: int | None,
    desc: str,
    unit: str,
    *,
    show: bool,
    leave: bool = False,
    initial: int = 0,
) -> Any:
    """A tqdm bar on a terminal, :class:`ProgressLines` elsewhere, a disabled bar if not ``show``.

    Args:
        total: how many items, or ``None`` when unknown.
        desc: the bar's label.
        unit: the items' name (singular).
        show: ``False``: no progress at all (``--no-progress``, ``-q``).
        leave: keep the finished bar on the terminal.
        initial: items done before (a resumed run).
    """
    from tqdm import tqdm  # type: ignore[import-untyped]

    if show and not stderr_is_terminal():
        return ProgressLines(total, desc, unit, initial=initial)
    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        disable=not show,
        file=sys.stderr,
        leave=leave,
        initial=initial,
    )
