"""tools/bench_phases.py: each step's memory charged to it, and a real run's table."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture(scope="module")
def tool(load_tool):
    return load_tool("bench_phases")


class Readings:
    """Resident memory that a test sets by hand, and a heap that counts its readings."""

    def __init__(self) -> None:
        self.value = 100.0
        self.heap_reads = 0

    def rss(self) -> float:
        return self.value

    def heap(self) -> tuple[float, float, float]:
        self.heap_reads += 1
        return (self.value / 2, 10.0 + self.heap_reads, 1.0)


def test_each_reading_is_charged_to_the_step_running(tool):
    mem = Readings()
    rec = tool.PhaseRecorder(mem.rss, mem.heap)

    def step(rise: float) -> str:
        mem.value += rise
        rec.sample()  # what the sampling thread reads during the call
        mem.value -= rise / 2
        return "done"

    solve = rec.mark("shading solve", step)
    cnn = rec.mark("Stage 0: CNN pass", step, numbered=False)
    assert cnn(50.0) == "done"  # the wrapped function's result comes back
    mem.value = 120.0
    assert solve(30.0) == "done" and solve(5.0) == "done" and solve(-10.0) == "done"
    mem.value = 400.0
    rec.sample()  # between the steps: the rest of the run
    rows = {row["step"]: row for row in rec.table()}
    assert list(rows) == [
        "Stage 0: CNN pass",
        "shading solve 1",
        "shading solve 2",
        "shading solve 3",
        tool.REST,
    ]
    assert rows["Stage 0: CNN pass"]["start"] == 100 and rows["Stage 0: CNN pass"]["peak"] == 150
    assert rows["shading solve 1"]["start"] == 120 and rows["shading solve 1"]["peak"] == 150
    assert rows["shading solve 2"]["start"] == 135 and rows["shading solve 2"]["peak"] == 140
    # a step whose memory only falls peaks at its start, where the heap is read
    assert rows["shading solve 3"]["start"] == rows["shading solve 3"]["peak"] == 137.5
    assert rows[tool.REST]["peak"] == 400
    # the heap is read at the first reading of each step's peak: in use, free, mapped
    assert rows["Stage 0: CNN pass"]["in_use"] == 75
    assert rows["Stage 0: CNN pass"]["free"] == 13  # the 3rd reading: REST's start, its start
    assert rows["shading solve 2"]["in_use"] == 70
    assert rows["shading solve 3"]["in_use"] == 137.5 / 2
    assert rows[tool.REST]["in_use"] == 200 and rows[tool.REST]["mapped"] == 1.0
    # memory that stays at a step's start is not read again (mallinfo2 takes the heap's lock)
    reads = mem.heap_reads
    rec.mark("flat", lambda: [rec.sample() for _ in range(3)])()
    assert mem.heap_reads == reads + 1 and rec.rows["flat 1"]["free"] == 10 + reads + 1


def test_without_a_heap_reader_the_columns_say_so(tool):
    mem = Readings()
    rec = tool.PhaseRecorder(mem.rss)
    rec.mark("reflectance solve", lambda: rec.sample())()
    text = tool.render({"rows": rec.table(), "process_peak": 100.0}, "title")
    lines = text.splitlines()
    assert lines[0] == "title"
    assert lines[3] == "| reflectance solve 1 | 100 | 100 | n/a | n/a | n/a |"
    assert lines[-1].startswith("| the whole process (VmHWM) | | 100 |")


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="reads /proc (Linux)")
def test_a_real_run_marks_every_step(tool, tmp_path, capsys):
    report = tmp_path / "phases.json"
    tool.main(["--size", "96", "--json", str(report)])
    result = json.loads(report.read_text())
    steps = [row["step"] for row in result["rows"]]
    expected = ["Stage 0: CNN pass", "Stage 0: proposals"]
    for k in range(1, 6):  # the default preset's five alternations
        expected += [f"shading solve {k}", f"reflectance terms {k}", f"reflectance solve {k}"]
    assert steps == [*expected, tool.REST]
    peaks = [row["peak"] for row in result["rows"]]
    # the readings see the process's peak (VmHWM), but for what lives under half a millisecond
    assert 0.8 * result["process_peak"] < max(peaks) <= result["process_peak"] + 1
    printed = capsys.readouterr().out
    assert "| reflectance solve 5 |" in printed and "(VmHWM)" in printed


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--photo", "nothing.png"], "no such file"),
        (["--size", "60"], "needs 90 px or more"),
        (["--json", "no/such/folder/out.json"], "its folder does not exist"),
    ],
)
def test_bad_arguments_are_one_line_errors_before_any_run(tool, tmp_path, monkeypatch, args, said):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        tool.main(args)
    assert said in str(stop.value) and "\n" not in str(stop.value)


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="reads /proc (Linux)")
def test_the_child_says_why_a_decomposition_failed(tool, tmp_path, monkeypatch):
    (tmp_path / "bad.png").write_bytes(b"not a png")
    monkeypatch.chdir(tmp_path)  # a path relative to the caller's folder
    with pytest.raises(SystemExit) as stop:
        tool.main(["--photo", "bad.png"])
    message = str(stop.value)
    assert "\n" not in message and "bad.png: is not an image" in message, message
