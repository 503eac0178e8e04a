"""``torchiid eval`` on the command line: notes, resuming, results folders, ``eval video``."""

import csv
import json
import re

import cv2
import numpy as np
import pytest
import torch

from torchiid.cli import main
from torchiid.eval import MITDataset
from torchiid.eval.video import write_flo
from torchiid.io import save_image, srgb_to_linear
from torchiid.synthetic import moving_mondrian


def _write16(path, arr):
    arr = np.round(np.clip(arr, 0, 1) * 65535).astype(np.uint16)
    if arr.ndim == 3:
        arr = arr[..., ::-1]
    assert cv2.imwrite(str(path), np.ascontiguousarray(arr))


def _fake_mit(root, names=("apple", "box", "cup"), h=48, w=48):
    """MIT-Berkeley's layout: ``<object>/{original,diffuse,reflectance,shading,mask}.png``."""
    for k, name in enumerate(names):
        rng = np.random.default_rng(k)
        d = root / name
        d.mkdir(parents=True)
        small = rng.random((h // 8 + 1, w // 8 + 1, 4)).astype(np.float32)
        smooth = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        refl = 0.15 + 0.75 * smooth[..., :3]
        refl[: h // 2, : w // 3] *= 0.5
        shading = 0.1 + 0.9 * smooth[..., 3]
        mask = np.zeros((h, w))
        mask[4:-4, 6:-6] = 1
        for fname, arr in (
            ("original", refl * shading[..., None]),
            ("diffuse", refl * shading[..., None]),
            ("reflectance", refl),
            ("shading", shading),
            ("mask", mask),
        ):
            _write16(d / f"{fname}.png", arr)
    return root


def _fake_iiw(root, h=32, w=40):
    root.mkdir(parents=True)
    rng = np.random.default_rng(3)
    cv2.imwrite(str(root / "1.png"), (rng.random((h, w, 3)) * 255).astype(np.uint8))
    points = [
        {"id": 0, "x": 0.25, "y": 0.5, "opaque": True},
        {"id": 1, "x": 0.75, "y": 0.5, "opaque": True},
    ]
    comparisons = [{"point1": 0, "point2": 1, "darker": "1", "darker_score": 1.0}]
    (root / "1.json").write_text(
        json.dumps({"intrinsic_points": points, "intrinsic_comparisons": comparisons})
    )
    return root


def _rows(out):
    with (out / "results.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def _notes(err):
    return [line for line in err.splitlines() if line.startswith("torchiid: note:")]


def _save_layers(folder, sample_id, reflectance, shading):
    save_image(folder / f"{sample_id}-reflectance.npy", reflectance, "npy")
    save_image(folder / f"{sample_id}-shading.npy", shading, "npy")


# ----------------------------------------------------------------------------- unused options


def test_options_that_do_not_apply_are_named_in_one_note(tmp_path, capsys):
    mit = _fake_mit(tmp_path / "mit", names=("apple",))
    iiw = _fake_iiw(tmp_path / "iiw")
    res = tmp_path / "res"
    s = MITDataset(mit)[0]
    _save_layers(res, "apple", s.image, torch.ones(1, 48, 48))
    cases = [
        (
            [
                "mit",
                mit,
                "--method",
                "r=i",
                "--delta",
                "0.2",
                "--flow",
                tmp_path,
                "--space",
                "linear",
            ],
            "--flow, --space (eval video only); --delta (iiw only)",
        ),
        (["iiw", iiw, "--method", "r=i", "--input", "original"], "--input (mit only)"),
        (
            ["mit", mit, "--method", "r=i", "--preset", "paper", "--iterations", "2"],
            "--preset, --iterations (--method semantic only)",
        ),
        (
            ["mit", mit, "--results", res, "--method", "retinex", "--batch-size", "2"]
            + ["--preset", "paper", "--iterations", "2", "--max-side", "0"],
            "--method, --batch-size, --preset, --iterations, --max-side (--results scores "
            "the layers in its folder as they are)",
        ),
    ]
    for k, (argv, named) in enumerate(cases):
        out = tmp_path / f"out{k}"
        assert main(["eval", *map(str, argv), "-o", str(out), "--no-progress"]) == 0
        err = capsys.readouterr().err
        dataset = argv[0]
        assert _notes(err) == [f"torchiid: note: not used by eval {dataset}: {named}"], err
        assert len(_rows(out)) == 1  # the run went on
    # options that apply draw no note; -q silences it
    argv = ["eval", "mit", str(mit), "--method", "r=i", "--input", "original", "--no-progress"]
    assert main([*argv, "-o", str(tmp_path / "plain"), "--batch-size", "2"]) == 0
    assert _notes(capsys.readouterr().err) == []
    assert main([*argv, "-o", str(tmp_path / "quiet"), "--delta", "0.1", "-q"]) == 0
    assert _notes(capsys.readouterr().err) == []
    argv = ["eval", "iiw", str(iiw), "--method", "r=i", "--delta", "0.2", "--no-progress"]
    assert main([*argv, "-o", str(tmp_path / "iiw-out")]) == 0
    assert _notes(capsys.readouterr().err) == []


# ----------------------------------------------------------------------------- resuming


def test_resume_refuses_a_selection_that_leaves_out_scored_ids(tmp_path, capsys):
    mit = _fake_mit(tmp_path / "mit")
    out = tmp_path / "out"
    ids = tmp_path / "ids.txt"
    ids.write_text("box\ncup\napple\n")
    base = ["eval", "mit", str(mit), "--method", "r=i", "-o", str(out), "--no-progress"]
    assert main([*base, "--ids", str(ids)]) == 0
    before = ((out / "results.csv").read_text(), (out / "summary.json").read_text())
    capsys.readouterr()
    assert main([*base, "--limit", "2"]) == 2  # apple, box: cup is scored but not selected
    err = capsys.readouterr().err.strip()
    assert err == (
        f"torchiid: error: {out} holds a run with other settings (ids: its results.csv "
        "scores cup, which this run does not select); use another -o or --overwrite"
    )
    assert ((out / "results.csv").read_text(), (out / "summary.json").read_text()) == before
    # a selection that includes every scored id goes on; summary and csv agree
    assert main([*base, "--ids", str(ids), "--limit", "3"]) == 0
    assert main([*base, "--overwrite", "--limit", "1"]) == 0
    assert main(base) == 0  # from the first object to all of them
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_images"] == summary["n_scored"] == len(_rows(out)) == 3


# ----------------------------------------------------------------------------- results folders


def test_a_layer_of_another_size_names_its_file(tmp_path, capsys):
    mit = _fake_mit(tmp_path / "mit", names=("apple",))
    res = tmp_path / "res"
    _save_layers(res, "apple", torch.rand(3, 40, 40) + 0.1, torch.ones(1, 48, 48))
    argv = ["eval", "mit", str(mit), "--results", str(res), "-o", str(tmp_path / "out")]
    assert main([*argv, "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert (
        f"torchiid: error: apple: reflectance {res / 'apple-reflectance.npy'} is (40, 40) but "
        "the image is (48, 48)"
    ) in err


def test_an_empty_results_folder_is_one_set_up_error(tmp_path, capsys):
    mit = _fake_mit(tmp_path / "mit")
    res = tmp_path / "res"
    res.mkdir()
    out = tmp_path / "out"
    argv = ["eval", "mit", str(mit), "--results", str(res), "-o", str(out), "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith(f"torchiid: error: {res}: no layers of any of")
    assert "<id>-reflectance.npy" in err and "apple-reflectance.npy" in err
    assert not (out / "results.csv").exists()


def test_layers_decomposed_from_the_srgb_decoded_input_draw_a_note(tmp_path, capsys):
    mit = _fake_mit(tmp_path / "mit", names=("apple", "box"))
    right, wrong = tmp_path / "right", tmp_path / "wrong"
    for s in MITDataset(mit):
        shading = s.image.mean(0, keepdim=True) + 0.05
        _save_layers(right, s.id, s.image / shading, shading)
        decoded = srgb_to_linear(s.image)  # the 16-bit linear file read as sRGB
        _save_layers(wrong, s.id, decoded / shading, shading)
    base = ["eval", "mit", str(mit), "--no-progress", "--results"]
    assert main([*base, str(right), "-o", str(tmp_path / "o1")]) == 0
    assert _notes(capsys.readouterr().err) == []
    assert main([*base, str(wrong), "-o", str(tmp_path / "o2")]) == 0  # scored as they are
    assert _notes(capsys.readouterr().err) == [
        f"torchiid: note: the layers of apple, box in {wrong} look decomposed from the image "
        "read as sRGB, but this dataset's images are linear: decompose them with torchiid "
        "decompose --linear"
    ]
    assert len(_rows(tmp_path / "o2")) == 2


def test_decompose_linear_of_flat_copies_scores_as_the_in_memory_run(tmp_path, capsys):
    # the recipe of the evaluation guide: flat <object>.png copies and masks, --linear
    mit = _fake_mit(tmp_path / "mit", names=("apple",), h=64, w=64)
    flat = tmp_path / "flat"
    flat.mkdir()
    (flat / "apple.png").symlink_to(mit / "apple" / "diffuse.png")
    (flat / "apple-mask.png").symlink_to(mit / "apple" / "mask.png")
    (flat / "list.csv").write_text("path,mask\napple.png,apple-mask.png\n")
    fast = ["--iterations", "1", "--no-progress"]
    res, srgb = tmp_path / "res", tmp_path / "srgb"
    argv = ["decompose", "--list", str(flat / "list.csv"), "--save-npy", *fast]
    assert main([*argv, "--linear", "-o", str(res)]) == 0
    assert main([*argv, "-o", str(srgb)]) == 0
    base = ["eval", "mit", str(mit), "--no-progress"]
    assert main([*base, "--iterations", "1", "-o", str(tmp_path / "memory")]) == 0
    assert main([*base, "--results", str(res), "-o", str(tmp_path / "r")]) == 0
    assert _notes(capsys.readouterr().err) == []
    memory, scored = _rows(tmp_path / "memory")[0], _rows(tmp_path / "r")[0]
    assert float(scored["lmse"]) == pytest.approx(float(memory["lmse"]), rel=1e-6)
    assert main([*base, "--results", str(srgb), "-o", str(tmp_path / "s")]) == 0
    assert "decompose them with torchiid decompose --linear" in capsys.readouterr().err


# ----------------------------------------------------------------------------- eval video


def test_eval_video_table_names_the_flows_it_used(tmp_path, capsys):
    seq = moving_mondrian(72, 96, frames=3, velocity=(2, 1), light_step=0.1)
    frames, res, flow = tmp_path / "frames", tmp_path / "res", tmp_path / "flow"
    flow.mkdir()
    for t, img in enumerate(seq.images):
        save_image(frames / f"frame_{t + 1:04d}.png", img, "srgb8")
        save_image(res / f"frame-{t + 1:06d}-reflectance.npy", seq.reflectance[t], "npy")
    for t in range(2):
        write_flo(flow / f"frame_{t + 1:04d}.flo", seq.flow[t])
    base = ["eval", "video", str(frames), str(res), "--no-progress"]
    assert main([*base, "--limit", "2", "--method", "r=i"]) == 0
    captured = capsys.readouterr()
    header = captured.out.splitlines()[0]
    assert header == (
        "warping error of the reflectance (srgb values in [0, 1]; est.: dis flow estimated "
        "on the frames)"
    )
    assert "given" not in captured.out and "WE (est.)" in captured.out
    assert _notes(captured.err) == [
        "torchiid: note: not used by eval video: --method, --limit (eval video scores the "
        "reflectance in RESULTS_DIR)"
    ]
    assert main([*base, "--flow", str(flow), "--eval-flow", "farneback"]) == 0
    out = capsys.readouterr().out
    header = out.splitlines()[0]
    assert header == (
        "warping error of the reflectance (srgb values in [0, 1]; est.: farneback flow "
        f"estimated on the frames; given: the .flo files in {flow} (2 of 2 pairs), occlusions "
        "from the forward-backward check)"
    )
    assert re.search(r"WE \(given\)\s+input given\s+valid given", out)


# ----------------------------------------------------------------------------- the guide


def test_the_guides_python_example_runs(tmp_path, monkeypatch):
    from pathlib import Path

    guide = Path(__file__).resolve().parents[2] / "docs" / "guide" / "evaluation.md"
    blocks = re.findall(r"```python\n(.*?)```", guide.read_text(), re.S)
    assert blocks, "the guide shows the Python API"
    mit = _fake_mit(tmp_path / "mit", names=("apple", "box"))
    monkeypatch.chdir(tmp_path)
    code = blocks[0].replace("path/to/mit-berkeley", str(mit))
    namespace: dict = {}
    exec(compile(code, str(guide), "exec"), namespace)  # noqa: S102 - the guide's own example
    rows, summary = namespace["rows"], namespace["summary"]
    assert list(rows) == ["apple", "box"] and summary["n_scored"] == 2
    # the sample scored directly: the r=i row of the run
    assert float(namespace["score"]) == pytest.approx(rows["apple"]["lmse"], rel=1e-9)
