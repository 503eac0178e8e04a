"""The Python API of evaluation runs (``torchiid.eval.EvalRunner`` / ``run_evaluation``)."""

import csv
import json

import cv2
import numpy as np
import pytest
import torch

from torchiid.baselines import reflectance_is_image, shading_is_image
from torchiid.core.exceptions import ParameterError, ShapeError, TorchiidError
from torchiid.eval import (
    METRICS,
    DatasetError,
    DenseFolderDataset,
    EvalResult,
    EvalRunner,
    dssim,
    load_layer,
    local_mse,
    method_parameters,
    open_dataset,
    run_evaluation,
    run_method,
    score_sample,
    si_mse,
)
from torchiid.io import save_image


def _write16(path, arr):
    arr = np.round(np.clip(arr, 0, 1) * 65535).astype(np.uint16)
    if arr.ndim == 3:
        arr = arr[..., ::-1]
    assert cv2.imwrite(str(path), np.ascontiguousarray(arr))


def _tiny_dense(root, sizes=((24, 32), (24, 32), (20, 28))):
    """A dense-GT folder: ``im<k>.png`` + ``-reflectance`` / ``-shading`` (+ one ``-mask``)."""
    root.mkdir(parents=True)
    for k, (h, w) in enumerate(sizes):
        rng = np.random.default_rng(k)
        refl = 0.15 + 0.75 * rng.random((h, w, 3))
        shading = 0.3 + 0.7 * rng.random((h, w, 1))
        _write16(root / f"im{k}.png", refl * shading)
        _write16(root / f"im{k}-reflectance.png", refl)
        _write16(root / f"im{k}-shading.png", shading[..., 0])
        if k == 0:
            mask = np.ones((h, w))
            mask[:4] = 0
            _write16(root / f"im{k}-mask.png", mask)
    return root


def _csv_rows(path):
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def test_run_evaluation_on_a_tiny_dense_folder(tmp_path):
    root = _tiny_dense(tmp_path / "dense")
    out = tmp_path / "out"
    result = run_evaluation("dense", root, method="s=i", output=out, device="cpu")
    assert isinstance(result, EvalResult) and result.ok and result.output == out
    assert result.ids == ("im0", "im1", "im2") and list(result.rows) == list(result.ids)
    assert result.columns == ("id", *METRICS["dense"], "seconds")
    for s in DenseFolderDataset(root):
        row = result.rows[s.id]
        layers = shading_is_image(s.image[None])
        m = s.mask[None]
        for name, gt, est in (
            ("reflectance", s.reflectance[None], layers.reflectance),
            ("shading", s.shading[None], layers.shading),
        ):
            assert row[f"si_mse_{name}"] == pytest.approx(float(si_mse(gt, est, m)[0]))
            assert row[f"lmse_{name}"] == pytest.approx(float(local_mse(gt, est, m)[0]))
            assert row[f"dssim_{name}"] == pytest.approx(
                float(dssim(gt, est, mask=m, scale_invariant=True)[0])
            )
        assert row["seconds"] >= 0
    # the files hold what the result holds
    assert json.loads(result.summary_path.read_text()) == result.summary
    on_disk = _csv_rows(result.csv_path)
    assert [r["id"] for r in on_disk] == list(result.ids)
    for r in on_disk:
        assert {c: float(v) for c, v in r.items() if c != "id"} == result.rows[r["id"]]
    summary = result.summary
    assert summary["method"] == "s=i" and summary["status"] == "complete"
    assert summary["n_images"] == summary["n_scored"] == 3 and summary["failures"] == []
    assert summary["mean"]["lmse_shading"] == pytest.approx(
        np.mean([r["lmse_shading"] for r in result.rows.values()])
    )


def test_runner_resumes_and_batches(tmp_path, monkeypatch):
    import torchiid.model as model

    root = _tiny_dense(tmp_path / "dense")
    out = tmp_path / "out"
    calls = []

    def fake(image, params=None, *, mask=None):
        calls.append(tuple(image.shape))
        return reflectance_is_image(image)

    monkeypatch.setattr(model, "decompose", fake)
    first = EvalRunner("dense", root, output=out, limit=1, device="cpu").run()
    assert list(first.rows) == ["im0"] and calls == [(1, 3, 24, 32)]
    assert first.summary["parameters"] == json.loads(json.dumps(method_parameters("semantic")))
    again = EvalRunner("dense", root, output=out, batch_size=2, device="cpu").run()
    assert list(again.rows) == ["im0", "im1", "im2"] and again.rows["im0"] == first.rows["im0"]
    assert sorted(calls[1:]) == [(1, 3, 20, 28), (1, 3, 24, 32)]  # im0 was not run again
    with pytest.raises(TorchiidError, match="exists"):
        EvalRunner("dense", root, output=out, resume=False, device="cpu").run()
    fresh = EvalRunner(
        "dense", root, output=out, overwrite=True, batch_size=2, ids=["im1", "im0"], device="cpu"
    ).run()
    assert fresh.ids == ("im1", "im0") and calls[-1] == (2, 3, 24, 32)


def test_runner_reports_failures(tmp_path):
    root = _tiny_dense(tmp_path / "dense")
    res = tmp_path / "res"
    for k, (h, w) in enumerate(((24, 32), (24, 32))):
        save_image(res / f"im{k}-reflectance.npy", torch.rand(3, h, w) + 0.1, "npy")
        save_image(res / f"im{k}-shading.npy", torch.rand(1, h, w) + 0.1, "npy")
    seen = []
    result = run_evaluation(
        "dense",
        root,
        method="retinex",  # ignored: the layers come from the results folder
        results_dir=res,
        output=tmp_path / "out",
        device="cpu",
        on_failure=lambda i, exc: seen.append((i, type(exc))),
    )
    assert not result.ok and list(result.rows) == ["im0", "im1"]
    assert seen == [("im2", TorchiidError)] and "im2-reflectance.npy" in result.failures["im2"]
    assert result.summary["method"] == "results" and result.summary["parameters"] == {}


def test_runner_checks_its_arguments(tmp_path):
    with pytest.raises(ParameterError, match="batch_size"):
        EvalRunner("dense", tmp_path, batch_size=0)
    with pytest.raises(ParameterError, match="limit"):
        EvalRunner("dense", tmp_path, limit=0)
    with pytest.raises(ParameterError, match="delta"):
        EvalRunner("iiw", tmp_path, delta=float("nan"))
    with pytest.raises(ParameterError, match="method"):
        EvalRunner("dense", tmp_path, method="magic")
    with pytest.raises(ParameterError, match="dataset"):
        EvalRunner("kitti", tmp_path)
    with pytest.raises(TorchiidError, match="does not exist"):
        EvalRunner("dense", tmp_path, results_dir=tmp_path / "nothing")
    runner = EvalRunner("mit", tmp_path, method="r=i", device="cpu")
    assert runner.output.name == "eval-mit-r=i" and runner.device == torch.device("cpu")


def test_open_dataset_ids(tmp_path):
    root = _tiny_dense(tmp_path / "dense")
    assert open_dataset("dense", root, ["im2", "im0"]).ids == ("im2", "im0")
    split = tmp_path / "split.txt"
    split.write_text("im1\n")
    assert open_dataset("dense", root, split).ids == ("im1",)
    with pytest.raises(DatasetError, match=r"1 of the given ids are not in .*\['im9'\]"):
        open_dataset("dense", root, ["im9"])
    split.write_text("im8\nim9\n")
    with pytest.raises(DatasetError, match="2 ids of .*split.txt are not in"):
        open_dataset("dense", root, split)


def test_run_method_and_parameters():
    image = torch.rand(2, 3, 8, 8) + 0.1
    out = run_method("r=i", image)
    assert torch.equal(out.reflectance, image) and torch.equal(out.shading, torch.ones(2, 1, 8, 8))
    out = run_method("retinex", image)
    assert torch.allclose(out.reflectance * out.shading, image, rtol=1e-5)
    with pytest.raises(ParameterError):
        run_method("magic", image)
    assert method_parameters("retinex")["threshold_gray"] == 0.075
    assert "mask" not in method_parameters("retinex") and method_parameters("s=i") == {}


def test_score_sample_checks_sizes(tmp_path):
    s = DenseFolderDataset(_tiny_dense(tmp_path / "dense"))[0]
    with pytest.raises(ShapeError, match="shading"):
        score_sample("dense", s, s.reflectance[None], torch.ones(1, 1, 5, 5))
    with pytest.raises(ParameterError):
        score_sample("kitti", s, s.reflectance[None], s.shading[None])


def test_load_layer_prefers_the_exact_files(tmp_path):
    r = torch.rand(3, 6, 7) * 0.8 + 0.1
    s = torch.rand(1, 6, 7) * 0.8 + 0.1
    with pytest.raises(TorchiidError, match="none of a-shading.npy, a-shading.exr, a-shading.png"):
        load_layer(tmp_path, "a", "shading")
    save_image(tmp_path / "a-reflectance.png", torch.zeros(3, 6, 7), "srgb8")
    save_image(tmp_path / "a-shading.png", torch.zeros(1, 6, 7), "srgb8")
    assert float(load_layer(tmp_path, "a", "reflectance").abs().max()) == 0.0
    save_image(tmp_path / "a-reflectance-linear16.png", r, "linear16")
    save_image(tmp_path / "a-shading.exr", s, "exr")
    got = load_layer(tmp_path, "a", "reflectance")
    assert got.shape == (1, 3, 6, 7) and torch.allclose(got[0], r, atol=1 / 65535)
    got = load_layer(tmp_path, "a", "shading")
    assert got.shape == (1, 1, 6, 7) and torch.allclose(got[0], s, rtol=1e-6)
    save_image(tmp_path / "a-shading.npy", 2 * s, "npy")
    assert torch.allclose(load_layer(str(tmp_path), "a", "shading")[0], 2 * s, rtol=1e-6)
    with pytest.raises(ParameterError):
        load_layer(tmp_path, "a", "albedo")
