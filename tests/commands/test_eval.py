import csv
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

import torchiid
import torchiid.cli as cli
import torchiid.model as model
from torchiid.baselines.retinex import color_retinex
from torchiid.commands.eval import run as run_eval
from torchiid.core.exceptions import ShapeError, TorchiidError
from torchiid.eval import (
    METRICS,
    DatasetError,
    DenseFolderDataset,
    IIWDataset,
    MITDataset,
    SAWDataset,
    dssim,
    local_mse,
    mit_lmse,
    run_evaluation,
    saw_ap,
    si_mse,
    whdr,
)
from torchiid.io import load_image, save_image

MIT_REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "mit-berkeley"


# ----------------------------------------------------------------------------- helpers


def _parse(argv):
    return cli.build_parser().parse_args(["eval", *[str(a) for a in argv]])


def _run(argv):
    return run_eval(_parse(argv))


def _main(argv):
    return cli.main(["eval", *[str(a) for a in argv]])


def _rows(out):
    with (out / "results.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def _smooth(rng, h, w, c, lo=0.15, hi=0.9):
    """A smooth random field (upsampled noise) in ``[lo, hi]``, (H, W, C)."""
    small = rng.random((h // 8 + 1, w // 8 + 1, c)).astype(np.float32)
    big = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, c)
    return lo + (hi - lo) * big


def _write16(path, arr):
    arr = np.round(np.clip(arr, 0, 1) * 65535).astype(np.uint16)
    if arr.ndim == 3:
        arr = arr[..., ::-1]
    assert cv2.imwrite(str(path), np.ascontiguousarray(arr))


def _fake_mit(root, names=("obj0", "obj1"), h=64, w=64):
    for k, name in enumerate(names):
        rng = np.random.default_rng(k)
        d = root / name
        d.mkdir(parents=True)
        refl = _smooth(rng, h, w, 3)
        refl[: h // 2, : w // 3] *= 0.5  # a reflectance edge
        shading = _smooth(rng, h, w, 1, 0.3, 1.0)[..., 0]
        image = refl * shading[..., None]
        mask = np.zeros((h, w))
        mask[4:-4, 6:-6] = 1
        for fname, arr in (
            ("original", image),
            ("diffuse", image),
            ("reflectance", refl),
            ("shading", shading),
            ("mask", mask),
        ):
            _write16(d / f"{fname}.png", arr)
    return root


def _fake_iiw(root, n=2, h=48, w=64):
    root.mkdir(parents=True)
    rng = np.random.default_rng(3)
    for k in range(1, n + 1):
        img = np.round(_smooth(rng, h, w, 3) * 255).astype(np.uint8)
        cv2.imwrite(str(root / f"{k}.png"), img[..., ::-1])
        pts = [
            {"id": i, "x": float(rng.random()), "y": float(rng.random()), "opaque": True}
            for i in range(12)
        ]
        comps = [
            {
                "point1": int(a),
                "point2": int(b),
                "darker": str(rng.choice(["1", "2", "E"])),
                "darker_score": float(rng.random() + 0.1),
            }
            for a, b in rng.integers(0, 12, (20, 2))
            if a != b
        ]
        (root / f"{k}.json").write_text(
            json.dumps({"intrinsic_points": pts, "intrinsic_comparisons": comps})
        )
    return root


def _fake_dense(root, sizes=((48, 64), (48, 64), (48, 64), (40, 56))):
    root.mkdir(parents=True)
    for k, (h, w) in enumerate(sizes):
        rng = np.random.default_rng(10 + k)
        refl = _smooth(rng, h, w, 3)
        shading = _smooth(rng, h, w, 1, 0.3, 1.0)
        _write16(root / f"im{k}.png", refl * shading)
        _write16(root / f"im{k}-reflectance.png", refl)
        _write16(root / f"im{k}-shading.png", shading[..., 0])
        if k == 0:
            mask = np.ones((h, w))
            mask[:8] = 0
            _write16(root / f"im{k}-mask.png", mask)
    return root


def _fake_saw(root, n=2, h=48, w=64):
    (root / "images").mkdir(parents=True)
    (root / "labels").mkdir()
    for k in range(n):
        rng = np.random.default_rng(20 + k)
        img = np.round(_smooth(rng, h, w, 3) * 255).astype(np.uint8)
        cv2.imwrite(str(root / "images" / f"{k}.png"), img[..., ::-1])
        lab = rng.choice([0, 1, 2, 100], size=(h, w)).astype(np.int64)
        np.save(root / "labels" / f"{k}.npy", lab)
    return root


def _trivial(method, image):
    """The r=i / s=i decompositions of a (1, 3, H, W) linear image."""
    if method == "r=i":
        return image, torch.ones_like(image[:, :1])
    return torch.ones_like(image), image.mean(1, keepdim=True)


class FakeDecompose:
    """Stands in for :func:`torchiid.model.decompose`: per-image, deterministic."""

    def __init__(self, fail_if_mean_below=None):
        self.batches = []
        self.fail_below = fail_if_mean_below

    def __call__(self, image, params=None, *, mask=None, **kw):
        self.batches.append((tuple(image.shape), None if mask is None else tuple(mask.shape)))
        if mask is not None:
            assert mask.dtype == torch.bool and mask.shape[1] == 1
        if self.fail_below is not None and bool((image.mean((1, 2, 3)) < self.fail_below).any()):
            raise ShapeError("synthetic failure")
        shading = image.mean(1, keepdim=True).sqrt()
        return SimpleNamespace(reflectance=image / shading, shading=shading)


# ----------------------------------------------------------------------------- tests


@pytest.mark.parametrize("method", ["r=i", "s=i"])
def test_mit_trivial_rows_equal_metric(tmp_path, method):
    root = _fake_mit(tmp_path / "mit")
    out = tmp_path / "out"
    assert _run(["mit", root, "--method", method, "-o", out, "--no-progress"]) == 0
    rows = _rows(out)
    assert list(rows[0]) == ["id", *METRICS["mit"], "seconds"]
    assert [r["id"] for r in rows] == ["obj0", "obj1"]
    for s, row in zip(MITDataset(root), rows, strict=True):
        r, sh = _trivial(method, s.image[None])
        m = s.mask[None]
        assert float(row["lmse"]) == pytest.approx(
            float(mit_lmse(s.reflectance[None], s.shading[None], r, sh, m)[0]), rel=1e-12
        )
        assert float(row["lmse_shading"]) == pytest.approx(
            float(local_mse(s.shading[None], sh, m)[0]), rel=1e-12
        )
        assert float(row["lmse_reflectance"]) == pytest.approx(
            float(
                local_mse(s.reflectance[None].mean(1, keepdim=True), r.mean(1, keepdim=True), m)[0]
            ),
            rel=1e-12,
        )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["dataset"] == "mit" and summary["method"] == method
    assert summary["torchiid_version"] == torchiid.__version__
    assert summary["n_images"] == summary["n_scored"] == 2 and summary["failures"] == []
    assert summary["status"] == "complete" and summary["median_seconds"] >= 0
    mean = np.mean([float(r["lmse"]) for r in rows])
    assert summary["mean"]["lmse"] == pytest.approx(mean)


def test_mit_retinex_and_table(tmp_path, capsys):
    root = _fake_mit(tmp_path / "mit", names=("obj0",))
    out = tmp_path / "out"
    assert _run(["mit", root, "--method", "retinex", "-o", out, "--no-progress"]) == 0
    s = MITDataset(root)[0]
    out_r = color_retinex(s.image[None], mask=s.mask[None])
    expect = float(
        mit_lmse(
            s.reflectance[None], s.shading[None], out_r.reflectance, out_r.shading, s.mask[None]
        )[0]
    )
    assert float(_rows(out)[0]["lmse"]) == pytest.approx(expect, rel=1e-6)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["parameters"]["threshold_gray"] == 0.075
    text = capsys.readouterr().out
    assert "obj0" in text and "mean" in text and f"{expect:.4f}" in text


def test_cli_and_python_api_agree(tmp_path):
    root = _fake_dense(tmp_path / "dense")
    cli_out, api_out = tmp_path / "cli", tmp_path / "api"
    argv = ["dense", root, "--method", "s=i", "--batch-size", "2", "--no-progress"]
    assert _run([*argv, "-o", cli_out]) == 0
    result = run_evaluation("dense", root, method="s=i", batch_size=2, output=api_out)
    rows = _rows(cli_out)
    assert [r["id"] for r in rows] == list(result.rows) == list(result.ids)
    for row in rows:
        assert [float(row[c]) for c in METRICS["dense"]] == [
            result.rows[row["id"]][c] for c in METRICS["dense"]
        ]
    summary, api = json.loads((cli_out / "summary.json").read_text()), dict(result.summary)
    for data in (summary, api):
        for key in ("started", "median_seconds"):
            data.pop(key)
    assert summary == api and list(summary) == list(api)


def test_iiw_whdr_and_delta(tmp_path):
    root = _fake_iiw(tmp_path / "iiw")
    out = tmp_path / "out"
    assert _run(["iiw", root, "--method", "r=i", "-o", out, "--no-progress", "--delta", "0.2"]) == 0
    rows = _rows(out)
    assert list(rows[0]) == ["id", "whdr", "seconds"]
    for s, row in zip(IIWDataset(root), rows, strict=True):
        assert float(row["whdr"]) == pytest.approx(whdr(s.image, s.judgements, delta=0.2))


def test_dense_metrics(tmp_path):
    root = _fake_dense(tmp_path / "dense")
    out = tmp_path / "out"
    assert _run(["dense", root, "--method", "s=i", "-o", out, "--no-progress"]) == 0
    rows = _rows(out)
    assert list(rows[0])[1:-1] == list(METRICS["dense"])
    for s, row in zip(DenseFolderDataset(root), rows, strict=True):
        r, sh = _trivial("s=i", s.image[None])
        m = s.mask[None]
        for name, gt, est in (
            ("reflectance", s.reflectance[None], r),
            ("shading", s.shading[None], sh),
        ):
            assert float(row[f"si_mse_{name}"]) == pytest.approx(float(si_mse(gt, est, m)[0]))
            assert float(row[f"lmse_{name}"]) == pytest.approx(float(local_mse(gt, est, m)[0]))
            assert float(row[f"dssim_{name}"]) == pytest.approx(
                float(dssim(gt, est, mask=m, scale_invariant=True)[0])
            )


def test_saw_pooled_ap(tmp_path, capsys):
    root = _fake_saw(tmp_path / "saw")
    out = tmp_path / "out"
    assert _run(["saw", root, "--method", "s=i", "-o", out, "--no-progress"]) == 0
    ds = SAWDataset(root)
    shadings = [s.image.mean(0, keepdim=True) for s in ds]
    labels = [s.labels for s in ds]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["pooled_ap"] == pytest.approx(saw_ap(shadings, labels))
    assert summary["pooled_ap_images"] == 2
    for sh, lab, row in zip(shadings, labels, _rows(out), strict=True):
        assert float(row["ap"]) == pytest.approx(saw_ap(sh, lab))
        assert int(row["n_smooth"]) == int((lab == 1).sum())
        assert int(row["n_boundary"]) == int(((lab == 2) | (lab == 3)).sum())
    assert "pooled AP" in capsys.readouterr().out


def test_results_folder_png_and_npy(tmp_path):
    root = _fake_mit(tmp_path / "mit")
    res = tmp_path / "res"
    res.mkdir()
    rng = torch.Generator().manual_seed(0)
    layers = {}
    for name in ("obj0", "obj1"):
        r = torch.rand(3, 64, 64, generator=rng) * 0.8 + 0.1
        s = torch.rand(1, 64, 64, generator=rng) * 0.8 + 0.1
        if name == "obj0":  # npy wins over a png of the same id
            save_image(res / f"{name}-reflectance.npy", r, "npy")
            save_image(res / f"{name}-shading.npy", s, "npy")
            save_image(res / f"{name}-reflectance.png", torch.ones(3, 64, 64), "srgb8")
        else:
            save_image(res / f"{name}-reflectance.png", r, "srgb8")
            save_image(res / f"{name}-shading.png", s, "srgb8")
            r = load_image(res / f"{name}-reflectance.png").image
            s = load_image(res / f"{name}-shading.png").image[:1]
        layers[name] = (r, s)
    out = tmp_path / "out"
    assert _run(["mit", root, "--results", res, "-o", out, "--no-progress"]) == 0
    for s, row in zip(MITDataset(root), _rows(out), strict=True):
        r, sh = layers[s.id]
        expect = mit_lmse(s.reflectance[None], s.shading[None], r[None], sh[None], s.mask[None])
        assert float(row["lmse"]) == pytest.approx(float(expect[0]), rel=1e-6)
    assert json.loads((out / "summary.json").read_text())["method"] == "results"


def test_results_folder_missing_file_is_a_failure(tmp_path):
    root = _fake_mit(tmp_path / "mit")
    res = tmp_path / "res"
    save_image(res / "obj0-reflectance.npy", torch.rand(3, 64, 64), "npy")
    save_image(res / "obj0-shading.npy", torch.rand(1, 64, 64) + 0.1, "npy")
    out = tmp_path / "out"
    assert _run(["mit", root, "--results", res, "-o", out, "--no-progress"]) == 1
    summary = json.loads((out / "summary.json").read_text())
    assert [f["id"] for f in summary["failures"]] == ["obj1"]
    assert "obj1-reflectance.npy" in summary["failures"][0]["error"]


def test_resume_limit_and_overwrite(tmp_path, monkeypatch):
    root = _fake_dense(tmp_path / "dense")
    out = tmp_path / "out"
    fake = FakeDecompose()
    monkeypatch.setattr(model, "decompose", fake)
    common = ["dense", root, "-o", out, "--no-progress", "--iterations", "1"]
    assert _run([*common, "--limit", "2"]) == 0
    assert len(fake.batches) == 2 and [r["id"] for r in _rows(out)] == ["im0", "im1"]
    first = _rows(out)
    assert _run(common) == 0  # resumes: only im2, im3 are decomposed
    assert len(fake.batches) == 4
    rows = _rows(out)
    assert [r["id"] for r in rows] == ["im0", "im1", "im2", "im3"] and rows[:2] == first
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_scored"] == 4 and summary["parameters"]["iterations"] == 1
    with pytest.raises(TorchiidError, match="--overwrite"):
        _run([*common, "--no-resume"])
    with pytest.raises(TorchiidError, match="other settings"):
        _run([*common[:-1], "2"])  # another parameter set on the same folder
    assert _run([*common, "--overwrite"]) == 0
    assert len(fake.batches) == 8 and len(_rows(out)) == 4


def test_resume_drops_torn_last_line(tmp_path):
    root = _fake_mit(tmp_path / "mit")
    out = tmp_path / "out"
    assert _run(["mit", root, "--method", "r=i", "-o", out, "--no-progress"]) == 0
    lines = (out / "results.csv").read_text().splitlines()
    (out / "results.csv").write_text("\n".join(lines[:2]) + "\n" + lines[2][:10])
    assert _run(["mit", root, "--method", "r=i", "-o", out, "--no-progress"]) == 0
    assert (out / "results.csv").read_text().splitlines()[:2] == lines[:2]
    assert [r["id"] for r in _rows(out)] == ["obj0", "obj1"]


def test_batches_group_equal_sizes(tmp_path, monkeypatch):
    root = _fake_dense(tmp_path / "dense")
    fake = FakeDecompose()
    monkeypatch.setattr(model, "decompose", fake)
    out1, out2 = tmp_path / "b1", tmp_path / "b2"
    assert _run(["dense", root, "-o", out1, "--no-progress", "--batch-size", "2"]) == 0
    assert sorted(b[0] for b in fake.batches) == [(1, 3, 40, 56), (1, 3, 48, 64), (2, 3, 48, 64)]
    assert all(b[1] == (b[0][0], 1, *b[0][2:]) for b in fake.batches)  # masks batched too
    assert _run(["dense", root, "-o", out2, "--no-progress"]) == 0
    metric = list(METRICS["dense"])
    for a, b in zip(_rows(out1), _rows(out2), strict=True):
        assert a["id"] == b["id"]
        np.testing.assert_allclose(
            [float(a[c]) for c in metric], [float(b[c]) for c in metric], rtol=1e-5
        )


def test_failing_image_in_batch_does_not_sink_the_others(tmp_path, monkeypatch):
    root = _fake_dense(tmp_path / "dense", sizes=((48, 64),) * 3)
    means = [s.image.mean().item() for s in DenseFolderDataset(root)]
    fake = FakeDecompose(fail_if_mean_below=min(means) + 1e-6)
    monkeypatch.setattr(model, "decompose", fake)
    out = tmp_path / "out"
    assert _run(["dense", root, "-o", out, "--no-progress", "--batch-size", "3"]) == 1
    bad = f"im{int(np.argmin(means))}"
    assert sorted(r["id"] for r in _rows(out)) == sorted({"im0", "im1", "im2"} - {bad})
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failures"] == [{"id": bad, "error": "synthetic failure"}]


def test_corrupt_image_recorded_and_exit_1(tmp_path, capsys):
    root = _fake_mit(tmp_path / "mit")
    (root / "obj0" / "diffuse.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    assert _main(["mit", root, "--method", "retinex", "-o", out, "--no-progress"]) == 1
    assert [r["id"] for r in _rows(out)] == ["obj1"]
    summary = json.loads((out / "summary.json").read_text())
    assert [f["id"] for f in summary["failures"]] == ["obj0"]
    assert "diffuse.png" in summary["failures"][0]["error"]
    err = capsys.readouterr().err
    assert "obj0" in err and "1 of 2 image(s) failed" in err


def test_bad_dir_is_one_line_error(tmp_path, capsys):
    missing = tmp_path / "nope"
    assert _main(["mit", missing, "--method", "r=i", "-o", tmp_path / "o", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("torchiid: error:") and str(missing) in err and "\n" not in err
    with pytest.raises(DatasetError):
        _run(["iiw", tmp_path, "--method", "r=i", "-o", tmp_path / "o2"])  # no photos there


def test_bad_options(tmp_path):
    root = _fake_mit(tmp_path / "mit", names=("obj0",))
    with pytest.raises(TorchiidError, match="batch-size"):
        _run(["mit", root, "--method", "r=i", "--batch-size", "0", "-o", tmp_path / "o"])
    with pytest.raises(TorchiidError, match="does not exist"):
        _run(["mit", root, "--results", tmp_path / "nothing", "-o", tmp_path / "o"])


def test_default_output_dir_and_progress(tmp_path, monkeypatch, capsys):
    root = _fake_mit(tmp_path / "mit", names=("obj0",))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: the bar is drawn
    assert _run(["mit", root, "--method", "s=i"]) == 0
    assert (tmp_path / "eval-mit-s=i" / "results.csv").is_file()
    assert "eval mit" in capsys.readouterr().err  # the tqdm bar
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)  # a log: lines, not a bar
    monkeypatch.setattr("torchiid.core.progress.EVERY", 0.0)  # a line at every image
    assert _run(["mit", root, "--method", "s=i", "-o", tmp_path / "again"]) == 0
    err = capsys.readouterr().err
    assert "eval mit: 1 of 1 imgs, " in err.splitlines()[0] and "\r" not in err


def test_ids_file_selects_and_orders(tmp_path):
    root = _fake_dense(tmp_path / "dense")
    ids = tmp_path / "split.txt"
    ids.write_text("# test split\nim2\nim0\n")
    out = tmp_path / "out"
    assert _run(["dense", root, "--method", "r=i", "--ids", ids, "-o", out, "--no-progress"]) == 0
    assert [r["id"] for r in _rows(out)] == ["im2", "im0"]
    ids.write_text("im9\n")
    with pytest.raises(DatasetError, match="im9"):
        _run(["dense", root, "--method", "r=i", "--ids", ids, "-o", tmp_path / "o2"])


@pytest.mark.slow
def test_semantic_end_to_end_tiny(tmp_path):
    root = _fake_mit(tmp_path / "mit", names=("obj0",), h=64, w=72)
    out = tmp_path / "out"
    assert _run(["mit", root, "-o", out, "--no-progress", "--iterations", "1"]) == 0
    assert np.isfinite(float(_rows(out)[0]["lmse"]))


@pytest.mark.skipif(not MIT_REAL.is_dir(), reason="MIT-Berkeley data not present")
def test_real_mit_limit(tmp_path):
    out = tmp_path / "out"
    assert (
        _run(["mit", MIT_REAL, "--method", "r=i", "--limit", "1", "-o", out, "--no-progress"]) == 0
    )
    assert len(_rows(out)) == 1
