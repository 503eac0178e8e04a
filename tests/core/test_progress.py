"""Progress on stderr: a bar on a terminal, a line now and then in a log."""

from __future__ import annotations

import io

import pytest

import torchiid.core.progress as progress_module
from torchiid.core.progress import ProgressLines, progress


@pytest.fixture
def clock(monkeypatch):
    """A clock the test moves: ``clock[0]`` seconds."""
    now = [1000.0]
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: now[0])
    return now


def test_a_line_at_most_every_interval_with_the_rate_and_the_time_left(clock):
    out = io.StringIO()
    lines = ProgressLines(400, "frames", "frame", every=30.0, file=out)
    clock[0] += 10
    lines.update(20)
    assert out.getvalue() == ""  # 10 s: too soon
    clock[0] += 50
    lines.update(100)  # 120 in 60 s: 2 per second, 280 left
    assert out.getvalue() == "frames: 120 of 400 frames, 2.0 frames/s, 2 min 20 s left\n"
    clock[0] += 1
    lines.update(1)
    assert out.getvalue().count("\n") == 1  # 1 s after the last line: none
    lines.close()
    assert out.getvalue().count("\n") == 1  # the command prints its own summary


def test_without_a_total_and_after_a_resumed_start(clock):
    out = io.StringIO()
    lines = ProgressLines(None, "eval iiw", "img", every=5.0, file=out)
    clock[0] += 8
    lines.update(4)
    assert out.getvalue() == "eval iiw: 4 imgs, 0.5 imgs/s\n"
    resumed = ProgressLines(100, "eval iiw", "img", every=5.0, file=out, initial=90)
    clock[0] += 10
    resumed.update(5)  # 5 in 10 s: the 90 done before do not count in the rate
    assert out.getvalue().splitlines()[-1] == "eval iiw: 95 of 100 imgs, 0.5 imgs/s, 10 s left"
    ProgressLines.write("torchiid: error: a frame", file=out)
    assert out.getvalue().endswith("\ntorchiid: error: a frame\n")


def test_progress_is_a_bar_on_a_terminal_and_lines_in_a_log(monkeypatch):
    from tqdm import tqdm

    monkeypatch.setattr(progress_module, "stderr_is_terminal", lambda: False)
    assert isinstance(progress(10, "frames", "frame", show=True), ProgressLines)
    off = progress(10, "frames", "frame", show=False)
    assert isinstance(off, tqdm) and off.disable
    monkeypatch.setattr(progress_module, "stderr_is_terminal", lambda: True)
    bar = progress(10, "frames", "frame", show=True, initial=3)
    assert isinstance(bar, tqdm) and not bar.disable and bar.n == 3
    bar.close()


@pytest.mark.parametrize(("done", "shown"), [(1, "0.1"), (30, "3.0"), (1234, "123")])
def test_the_rate_reads_as_a_plain_number(clock, done, shown):
    out = io.StringIO()
    lines = ProgressLines(None, "eval mit", "img", every=1.0, file=out)
    clock[0] += 10
    lines.update(done)
    assert out.getvalue() == f"eval mit: {done} imgs, {shown} imgs/s\n"
