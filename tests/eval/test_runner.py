"""The Python API of evaluation runs (``torchiid.eval.EvalRunner`` / ``run_evaluation``)."""

import csv
import json

import cv2
import numpy as np
import pytest
import torch

from torchiid.baselines import reflectance_is_image, shading_is_image
from torchiid.core.exceptions import ParameterError, TorchiidError
from torchiid.eval import (
    METRICS,
    DenseFolderDataset,
    EvalOptions,
    EvalResult,
    EvalRunner,
    dssim,
    local_mse,
    method_parameters,
    run_evaluation,
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
    first = EvalRunner("dense", root, EvalOptions(output=out, limit=1, device="cpu")).run()
    assert list(first.rows) == ["im0"] and calls == [(1, 3, 24, 32)]
    assert first.summary["parameters"] == json.loads(json.dumps(method_parameters("semantic")))
    again = EvalRunner("dense", root, EvalOptions(output=out, batch_size=2, device="cpu")).run()
    assert list(again.rows) == ["im0", "im1", "im2"] and again.rows["im0"] == first.rows["im0"]
    assert sorted(calls[1:]) == [(1, 3, 20, 28), (1, 3, 24, 32)]  # im0 was not run again
    with pytest.raises(TorchiidError, match="exists"):
        EvalRunner("dense", root, EvalOptions(output=out, resume=False, device="cpu")).run()
    options = EvalOptions(
        output=out, overwrite=True, batch_size=2, ids=["im1", "im0"], device="cpu"
    )
    fresh = EvalRunner("dense", root, options).run()
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
    with pytest.raises(ParameterError, match="dataset"):
        EvalRunner("kitti", tmp_path)
    with pytest.raises(TorchiidError, match="does not exist"):
        EvalRunner("dense", tmp_path, EvalOptions(results_dir=tmp_path / "nothing"))
    (tmp_path / "file").write_text("")
    with pytest.raises(TorchiidError, match="is a file, not a dense dataset directory"):
        EvalRunner("dense", tmp_path / "file")
    runner = EvalRunner("mit", tmp_path, EvalOptions(method="r=i", device="cpu"))
    assert runner.output.name == "eval-mit-r=i" and runner.device == torch.device("cpu")
    assert runner.method == "r=i" and runner.batch_size == 1 and runner.delta == 0.10
    scoring = EvalRunner("mit", tmp_path, EvalOptions(results_dir=tmp_path))
    assert scoring.method == "results" and scoring.output.name == "eval-mit-results"
    with pytest.raises(AttributeError, match="no attribute 'magic'"):
        runner.magic  # noqa: B018


def test_the_settings_are_no_keywords_of_the_runner(tmp_path):
    # EvalOptions holds them (run_evaluation takes them as keywords)
    with pytest.raises(TypeError, match="unexpected keyword argument 'method'"):
        EvalRunner("dense", tmp_path, method="s=i")
    with pytest.raises(TypeError, match="unexpected keyword argument 'batch_size'"):
        EvalRunner("dense", tmp_path, EvalOptions(method="s=i"), batch_size=2)
