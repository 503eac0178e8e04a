import json

import cv2
import numpy as np
import pytest
from skimage import data

from torchiid.cli import main
from torchiid.params import Parameters

FAST = ["--iterations", "1", "--no-progress"]


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    d = tmp_path_factory.mktemp("photos")
    cat = cv2.resize(data.chelsea(), (96, 72), interpolation=cv2.INTER_AREA)
    coffee = cv2.resize(data.coffee(), (96, 72), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(d / "cat.png"), cat[..., ::-1])
    cv2.imwrite(str(d / "coffee.jpg"), coffee[..., ::-1])
    return d


def test_decompose_writes_viewable_layers_and_parameters(photos, tmp_path):
    out = tmp_path / "out"
    assert (
        main(
            [
                "decompose",
                str(photos / "cat.png"),
                "-o",
                str(out),
                "--save-npy",
                "--save-iterations",
                *FAST,
            ]
        )
        == 0
    )
    refl = cv2.imread(str(out / "cat-reflectance.png"), cv2.IMREAD_UNCHANGED)
    shad = cv2.imread(str(out / "cat-shading.png"), cv2.IMREAD_UNCHANGED)
    prev = cv2.imread(str(out / "cat-preview.png"), cv2.IMREAD_UNCHANGED)
    assert refl.shape == (72, 96, 3) and refl.dtype == np.uint8
    assert shad.shape[:2] == (72, 96) and prev.shape == (72, 3 * 96 + 8, 3)
    lin = cv2.imread(str(out / "cat-reflectance-linear16.png"), cv2.IMREAD_UNCHANGED)
    assert lin.dtype == np.uint16 and lin.shape == (72, 96, 3)
    r = np.load(out / "cat-reflectance.npy")
    s = np.load(out / "cat-shading.npy")
    # the linear layers multiply back to the linear input
    from torchiid.io import load_image

    img = load_image(photos / "cat.png").image.permute(1, 2, 0).numpy()
    assert s.shape == (72, 96)
    assert np.allclose(r * s[..., None], img, atol=1e-5)
    # the parameters file is the format --params reads back
    params = Parameters.from_json(out / "cat-params.json")
    assert params == Parameters.preset("default").replace(iterations=1)
    assert (out / "cat-iter1-sigma.png").exists() and (out / "cat-iter1-R.png").exists()
    assert not list(out.glob(".*"))  # no temporary files left behind


def test_existing_outputs_are_not_overwritten(photos, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["decompose", str(photos / "cat.png"), "-o", str(out), *FAST]) == 0
    before = (out / "cat-reflectance.png").read_bytes()
    assert main(["decompose", str(photos / "cat.png"), "-o", str(out), *FAST]) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().err  # done: the manifest says so
    assert main(["decompose", str(photos / "cat.png"), "-o", str(out), "--redo", *FAST]) == 1
    assert "exists (--redo runs every input again); pass --overwrite" in capsys.readouterr().err
    assert (out / "cat-reflectance.png").read_bytes() == before
    assert main(["decompose", str(photos / "cat.png"), "-o", str(out), "--overwrite", *FAST]) == 0


def test_directory_with_a_bad_file_processes_the_rest(photos, tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    for name in ("cat.png", "coffee.jpg"):
        (src / name).write_bytes((photos / name).read_bytes())
    (src / "broken.png").write_text("not an image")
    out = tmp_path / "out"
    assert main(["decompose", str(src), "-o", str(out), *FAST]) == 1
    err = capsys.readouterr().err
    assert "broken.png: is not an image" in err and "1 of 3 input(s) failed" in err
    assert "Traceback" not in err
    assert (out / "cat-reflectance.png").exists() and (out / "coffee-shading.png").exists()
    assert not (out / "broken-reflectance.png").exists()


def test_retinex_method_and_mask(photos, tmp_path):
    mask = np.zeros((72, 96), np.uint8)
    mask[10:60, 10:80] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    out = tmp_path / "out"
    assert (
        main(
            [
                "decompose",
                str(photos / "cat.png"),
                "-o",
                str(out),
                "--method",
                "retinex",
                "--mask",
                str(tmp_path / "mask.png"),
                "--save-npy",
                "--no-progress",
            ]
        )
        == 0
    )
    assert json.loads((out / "cat-params.json").read_text())["method"] == "color_retinex"
    out2 = tmp_path / "out2"
    assert (
        main(
            [
                "decompose",
                str(photos / "cat.png"),
                "-o",
                str(out2),
                "--mask",
                str(tmp_path / "mask.png"),
                "--save-npy",
                *FAST,
            ]
        )
        == 0
    )
    r = np.load(out2 / "cat-reflectance.npy")
    assert np.all(r[:10] == 0) and np.all(r[60:] == 0) and r[30, 40].sum() > 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["decompose", "missing.png", "-o", "{out}"], "missing.png: no such file"),
        (["decompose", "{cat}", "-o", "{out}", "--preset", "fastest"], "unknown preset"),
        (["decompose", "{cat}", "-o", "{out}", "--variant", "v9"], "unknown variant"),
        (["decompose", "{cat}", "-o", "{out}", "--params", "{bad}"], "Invalid parameter: foo"),
        (["decompose", "{cat}", "-o", "{out}", "--iterations", "0"], "--iterations must be"),
        (["decompose", "{cat}", "-o", "{cat}"], "is not a directory"),
    ],
)
def test_errors_are_one_line_without_traceback(photos, tmp_path, capsys, args, message):
    (tmp_path / "bad.json").write_text('{"foo": 1}')
    subs = {
        "out": str(tmp_path / "out"),
        "cat": str(photos / "cat.png"),
        "bad": str(tmp_path / "bad.json"),
    }
    argv = [a.format(**subs) for a in args] + ["--no-progress"]
    assert main(argv) != 0
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_cuda_request_without_cuda_is_a_clear_error(photos, tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    assert (
        main(["decompose", str(photos / "cat.png"), "-o", str(tmp_path), "--device", "cuda", *FAST])
        == 2
    )
    assert "no CUDA device is available" in capsys.readouterr().err


def _srgb_decode(a):
    import torch

    from torchiid.io import srgb_to_linear

    x = torch.from_numpy(a.astype(np.float32) / 255)
    return srgb_to_linear(x).numpy()


def test_output_files_keep_the_convention_users_rely_on(tmp_path):
    """Exact files multiply back to the image; the viewable ones do up to shading_white."""
    import torch

    from torchiid.io import load_image, read_exr

    src = tmp_path / "coffee.png"
    cv2.imwrite(
        str(src), cv2.resize(data.coffee(), (180, 120), interpolation=cv2.INTER_AREA)[..., ::-1]
    )
    out = tmp_path / "out"
    argv = ["decompose", str(src), "-o", str(out), "--save-confidence", "--iterations", "2"]
    assert main([*argv, "--no-progress"]) == 0
    img = load_image(src).image.permute(1, 2, 0).numpy()
    info = json.loads((out / "coffee-info.json").read_text())
    white = info["shading_white"]
    assert len(info["solves"]) == 4 and isinstance(info["converged"], bool)
    assert info["size"] == [180, 120] and 0 <= info["albedo_excess"] <= 0.001 + 1 / (180 * 120)
    assert set(info["files"]) >= {"coffee-shading.exr", "coffee-reflectance-linear16.png"}
    # exact pair: 16-bit linear reflectance (not clipped) and float OpenEXR shading
    r16 = cv2.imread(str(out / "coffee-reflectance-linear16.png"), cv2.IMREAD_UNCHANGED)
    r = r16[..., ::-1].astype(np.float64) / 65535
    s, meta = read_exr(out / "coffee-shading.exr")
    assert s.dtype == np.float32 and s.shape == (120, 180)
    assert float(meta["shading_white"]) == pytest.approx(white)
    assert (r16 == 65535).mean() <= 0.001 * 3  # only the quantile's pixels reach 1
    # 16-bit R: relative error at most 1 / (2 * 65535 * R) per channel, plus the gray fit
    rel = np.abs(r * s[..., None] - img) / np.maximum(img, 1e-6)
    assert rel[r > 0.02].max() < 1e-3 and np.median(rel[r > 0.02]) < 1e-4
    assert s.max() > 0 and np.isfinite(s).all()
    # viewable pair: R8 * S8 * shading_white = I (median relative error < 3%, bright pixels)
    r8 = cv2.imread(str(out / "coffee-reflectance.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    s8 = cv2.imread(str(out / "coffee-shading.png"), cv2.IMREAD_UNCHANGED)
    recon = _srgb_decode(r8) * _srgb_decode(s8)[..., None] * white
    lit = img > 0.05 * img.max()
    assert np.median(np.abs(recon - img)[lit] / img[lit]) < 0.03
    conf = cv2.imread(str(out / "coffee-confidence.png"), cv2.IMREAD_UNCHANGED)
    assert conf.dtype == np.uint8 and conf.shape == (120, 180)
    prev = cv2.imread(str(out / "coffee-preview.png"), cv2.IMREAD_UNCHANGED)
    assert prev.shape == (120, 3 * 180 + 8, 3)
    # eval --results scores the exact files when present
    from torchiid.eval.results import load_layer

    refl = load_layer(out, "coffee", "reflectance")
    assert torch.allclose(refl[0].permute(1, 2, 0), torch.from_numpy(r).float(), atol=1e-6)
    shad = load_layer(out, "coffee", "shading")
    assert torch.allclose(shad[0, 0], torch.from_numpy(s), rtol=1e-6)


def test_large_photos_get_a_downscaled_preview_and_full_size_layers(tmp_path):
    src = tmp_path / "wide.jpg"
    big = cv2.resize(data.coffee(), (1200, 800), interpolation=cv2.INTER_CUBIC)
    cv2.imwrite(str(src), big[..., ::-1])
    out = tmp_path / "out"
    assert main(["decompose", str(src), "-o", str(out), "--iterations", "1", "--no-progress"]) == 0
    info = json.loads((out / "wide-info.json").read_text())
    assert info["working_size"] == [512, 341] and info["size"] == [1200, 800]
    refl = cv2.imread(str(out / "wide-reflectance.png"), cv2.IMREAD_UNCHANGED)
    assert refl.shape == (800, 1200, 3)
    prev = cv2.imread(str(out / "wide-preview.png"), cv2.IMREAD_UNCHANGED)
    assert prev.shape == (683, 3 * 1024 + 8, 3)


def test_retinex_output_follows_the_readme_convention(photos, tmp_path):
    """--method retinex: R is an albedo in [0, 1] (99.9th percentile of max_c R_c is 1),
    R * S == I, shading_white is the shading's 99th percentile, like the method's output."""
    out = tmp_path / "out"
    argv = ["decompose", str(photos / "cat.png"), "-o", str(out), "--method", "retinex"]
    assert main([*argv, "--save-npy", "--no-progress"]) == 0
    from torchiid.io import load_image

    img = load_image(photos / "cat.png").image.permute(1, 2, 0).numpy()
    r, s = np.load(out / "cat-reflectance.npy"), np.load(out / "cat-shading.npy")
    info = json.loads((out / "cat-info.json").read_text())
    assert info["method"] == "retinex" and r.max() <= 1
    assert (s >= img.max(axis=2) - 1e-6).all()  # R <= 1, so S >= max_c I_c
    assert np.quantile(r.max(axis=2), 0.999, method="higher") == pytest.approx(1, abs=2e-3)
    assert np.allclose(r * s[..., None], img, atol=1e-5)
    assert info["shading_white"] == pytest.approx(np.quantile(s, 0.99), rel=1e-2)
    s8 = cv2.imread(str(out / "cat-shading.png"), cv2.IMREAD_UNCHANGED)
    assert np.quantile(s8, 0.99) >= 254  # shading / shading_white: the 99th percentile is white


def test_error_lines_go_above_the_progress_bar(photos, tmp_path, capsys):
    argv = ["decompose", "missing.png", str(photos / "cat.png"), "-o", str(tmp_path / "o")]
    assert main([*argv, "--iterations", "1"]) == 1  # progress bar on
    err = capsys.readouterr().err
    line = next(x for x in err.split("\n") if "missing.png" in x)
    assert line.split("\r")[-1] == "torchiid: error: missing.png: no such file"


def test_no_inputs_and_conflicting_options_are_usage_errors(photos, tmp_path, capsys):
    assert main(["decompose", "-o", str(tmp_path / "o")]) == 2
    assert (
        "no inputs: name image files, folders or globs, or --list FILE" in capsys.readouterr().err
    )
    argv = ["decompose", str(photos / "cat.png"), "-o", str(tmp_path / "o")]
    assert main([*argv, "--workers", "2", "--dask-scheduler", "tcp://x:1"]) == 2
    assert "--workers and --dask-scheduler exclude each other" in capsys.readouterr().err
    assert main([*argv, "--workers", "0"]) == 2
    assert "--workers must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("how", ["folder", "glob"])
def test_an_input_folder_that_is_the_output_folder_is_run_again_as_done(photos, tmp_path, how):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "cat.png").write_bytes((photos / "cat.png").read_bytes())
    source = str(folder) if how == "folder" else str(folder / "*.png")
    argv = ["decompose", source, "-o", str(folder), *FAST]
    assert main(argv) == 0
    assert (folder / "cat-reflectance.png").is_file() and (folder / "cat-shading.exr").is_file()
    made = sorted(p.name for p in folder.iterdir())
    # again: its outputs are not new inputs, and the photo is done
    assert main(argv) == 0
    assert sorted(p.name for p in folder.iterdir()) == made
    records = [json.loads(line) for line in (folder / "manifest.jsonl").read_text().splitlines()]
    assert [r["key"] for r in records] == ["cat"]


def test_an_alpha_channel_that_leaves_pixels_out_is_a_note(photos, tmp_path, capsys):
    rgb = cv2.imread(str(photos / "cat.png"))
    alpha = np.full(rgb.shape[:2], 255, np.uint8)
    cv2.imwrite(str(tmp_path / "opaque.png"), np.dstack([rgb, alpha]))
    alpha[:, : rgb.shape[1] // 4] = 0  # the left quarter transparent
    cv2.imwrite(str(tmp_path / "holes.png"), np.dstack([rgb, alpha]))
    out = tmp_path / "out"
    argv = ["decompose", str(tmp_path / "holes.png"), str(tmp_path / "opaque.png"), "-o", str(out)]
    assert main([*argv, *FAST]) == 0
    err = capsys.readouterr().err
    note = (
        f"torchiid: note: {tmp_path / 'holes.png'}: its alpha channel is the mask: the 25.0% of "
        "its pixels that are at most half opaque are left out (0 in the layers)"
    )
    assert note in err.splitlines() and "opaque.png: its alpha" not in err
    info = {s: json.loads((out / f"{s}-info.json").read_text()) for s in ("holes", "opaque")}
    assert info["holes"]["alpha_mask"] is True and info["opaque"]["alpha_mask"] is True
    refl = cv2.imread(str(out / "holes-reflectance.png"))
    assert not refl[:, : rgb.shape[1] // 4].any()


def test_files_that_are_not_this_decomposition_say_why_they_are_not_skipped(
    photos, tmp_path, capsys
):
    photo = tmp_path / "cat.png"
    photo.write_bytes((photos / "cat.png").read_bytes())
    out = tmp_path / "out"
    argv = ["decompose", str(photo), "-o", str(out), "--no-progress"]
    assert main([*argv, "--iterations", "1"]) == 0
    capsys.readouterr()
    target = out / "cat-reflectance-linear16.png"
    for extra, why in [
        (["--iterations", "2"], "written with other parameters"),
        (["--iterations", "1", "--redo"], "--redo runs every input again"),
    ]:
        assert main([*argv, *extra]) == 1
        assert f"{target} exists ({why}); pass --overwrite to replace it" in capsys.readouterr().err
    cv2.imwrite(str(photo), cv2.imread(str(photos / "cat.png"))[::-1])  # the photo changed
    assert main([*argv, "--iterations", "1"]) == 1
    why = f"decomposed from another version of {photo}, or from another file"
    assert f"{target} exists ({why}); pass --overwrite" in capsys.readouterr().err


def test_the_decomposition_edit_wrote_is_named_as_edit_s(photos, tmp_path, capsys):
    out = tmp_path / "out"
    photo = str(photos / "cat.png")
    assert main(["edit", "merge", photo, "-o", str(out), "--iterations", "1", "-q"]) == 0
    assert main(["decompose", photo, "-o", str(out), *FAST]) == 1
    why = "written by torchiid edit, with no record of its parameters"
    assert f"cat-reflectance-linear16.png exists ({why})" in capsys.readouterr().err


def test_the_outputs_stay_out_of_the_inputs_after_a_failed_rerun_and_through_a_link(
    photos, tmp_path, capsys
):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "cat.png").write_bytes((photos / "cat.png").read_bytes())
    (tmp_path / "link").symlink_to(folder, target_is_directory=True)
    argv = ["decompose", str(folder), "-o", str(folder), *FAST]
    assert main(argv) == 0
    assert main([*argv, "--save-npy"]) == 1  # other parameters: cat fails, its files stay
    assert "exists (written with other parameters)" in capsys.readouterr().err
    for source in (folder, tmp_path / "link"):  # its last record failed; the files are still its
        assert main(["decompose", str(source), "-o", str(folder), *FAST]) == 0
        assert ", 0 failed" in capsys.readouterr().err  # cat alone: its files found complete
    records = [json.loads(line) for line in (folder / "manifest.jsonl").read_text().splitlines()]
    assert {r["key"] for r in records} == {"cat"}
