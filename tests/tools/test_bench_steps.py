"""tools/bench_steps.py: every step measured and tabled, on tiny photos (no timing judged)."""

from __future__ import annotations

import re

import pytest
import torch


@pytest.fixture(scope="module")
def tool(load_tool):
    return load_tool("bench_steps")


def test_every_step_is_measured_and_tabled(tool, tmp_path):
    from torchiid.params import Parameters

    photos = tool.make_photos(tmp_path / "photos", 96, 64)
    params = Parameters.preset("default").replace(iterations=1)
    results = {
        ("cpu", n): tool.measure(photos[:n], tmp_path / f"out{n}", "cpu", params, 1, warm_up=False)
        for n in (1, 2)
    }
    # the files the command writes, for every photo of the batch
    for photo in photos[:2]:
        assert (tmp_path / "out2" / f"{photo.stem}-reflectance.png").is_file()
        assert (tmp_path / "out2" / f"{photo.stem}-sigma.exr").is_file()
        assert (tmp_path / "out2" / f"{photo.stem}-info.json").is_file()
    text = tool.table(results, k=1)
    lines = text.splitlines()
    assert lines[0] == "| step | cpu, batch of 1 | cpu, batch of 2 (per photo) |"
    rows = {line.split(" | ")[0].lstrip("| "): line for line in lines[2:]}
    expected = [
        "decode",
        "CNN patch features",
        "proposals (selective search)",
        "PCA / mid-level features",
        "texture marks of S_l",
        "shading solve 1",
        "reflectance solve 1",
        "outputs",
        "total",
        "peak memory, worker RSS (GB)",
    ]
    for name in expected:
        assert name in rows, name
        values = [float(v) for v in re.findall(r"\| ([-\d.]+)", rows[name])]
        # the table rounds to milliseconds: a tiny photo's decode can print as 0.000
        assert len(values) == 2 and all(v >= 0 for v in values), rows[name]
    assert "shading solve 2" not in rows
    for res in results.values():
        steps = res["steps"]
        assert all(v > 0 for v in steps.values()), steps  # every step measured, unrounded
        parts = sum(v for k, v in steps.items() if k != "total")
        assert steps["total"] == pytest.approx(parts, rel=1e-9)  # one repeat: the parts add up


@pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is present")
def test_cuda_without_a_device_is_a_one_line_error(tool):
    with pytest.raises(SystemExit) as stop:
        tool.main(["--device", "cuda", "--size", "96"])
    message = str(stop.value)
    assert "\n" not in message and "no CUDA device" in message
