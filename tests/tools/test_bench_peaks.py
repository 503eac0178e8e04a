"""tools/bench_peaks.py: the split of a run's memory into the CNN pass and what follows."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def tool(load_tool):
    return load_tool("bench_peaks")


def test_the_first_fall_after_the_floor_ends_the_first_part(tool):
    # rising to the pass's 600, handed back to 400, then a second peak of 590
    samples = [50, 300, 600, 580, 400, 450, 590, 560]
    assert tool.split_peaks(samples, floor=400, drop=100) == (600, 590)
    # a fall of less than `drop` does not end it: the later 620 still belongs to the first part
    assert tool.split_peaks([50, 500, 450, 620, 300, 350], 400, 100) == (620, 350)
    # a fall before the memory passed the floor is start-up, not the hand-back
    assert tool.split_peaks([300, 100, 500, 350, 420], 400, 100) == (500, 420)


def test_a_run_without_the_hand_back_is_one_part(tool):
    first, after = tool.split_peaks([50, 300, 350], 400, 100)
    assert first == 350 and math.isnan(after)
    with pytest.raises(ValueError, match="no memory samples"):
        tool.split_peaks([], 400, 100)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
def test_a_process_that_frees_a_block_shows_two_peaks(tool):
    code = (
        "import time\n"
        "a = bytearray(300 << 20); time.sleep(0.3)\n"  # bytearray() writes every page
        "del a; time.sleep(0.2)\n"
        "b = bytearray(80 << 20); time.sleep(0.3)\n"
    )
    samples = tool.sample_run([sys.executable, "-c", code], env=None)
    first, after = tool.split_peaks(samples, floor=250, drop=150)
    assert first > 300 and after < first - 150 and after > 80
