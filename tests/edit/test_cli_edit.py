"""``torchiid edit``: outputs, --from reuse, no-overwrite and one-line errors."""

import numpy as np
import pytest
import torch

from torchiid.cli import main
from torchiid.io import load_image, save_image
from torchiid.synthetic import mondrian


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("edit")
    save_image(d / "m.png", mondrian(64, 80, seed=2).image[0], "srgb8")
    m = torch.zeros(1, 64, 80)
    m[:, 20:40, 20:60] = 1
    save_image(d / "mask.png", m, "srgb8")
    save_image(d / "tex.png", torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0)))
    out = d / "dec"
    assert main(["edit", "merge", str(d / "m.png"), "-o", str(out), "--iterations", "1"]) == 0
    return d, out


def test_merge_writes_result_layers_and_reusable_decomposition(files):
    d, out = files
    for name in ["m-merge.png", "m-merge.exr", "m-merge-C.exr", "m-merge-shading.png",
                 "m-merge-info.json", "m-reflectance-linear16.png", "m-shading.exr",
                 "m-sigma.exr", "m-rho.exr"]:  # fmt: skip
        assert (out / name).is_file(), name
    # the merged components reconstruct the input (8-bit rounding)
    a = load_image(d / "m.png").image
    b = load_image(out / "m-merge.png").image
    assert float((a - b).abs().max()) < 0.02


@pytest.mark.parametrize(
    "argv",
    [
        ["recolour", "--mask", "mask.png", "--hue", "90"],
        ["remove-texture", "--mask", "mask.png"],
        ["replace-albedo", "--mask", "mask.png", "--texture", "tex.png"],
        ["illumination-colour", "--tint", "green"],
        ["illumination-intensity", "--combine", "e2"],
        ["soften-shadows", "--amount", "0.5"],
    ],
)
def test_operations_from_saved_decomposition(files, tmp_path, argv):
    d, out = files
    op, opts = argv[0], [str(d / a) if a.endswith(".png") else a for a in argv[1:]]
    assert main(["edit", op, str(d / "m.png"), "--from", str(out), "-o", str(tmp_path), *opts]) == 0
    res = load_image(tmp_path / f"m-{op}.png").image
    assert res.shape == (3, 64, 80)
    assert not list(tmp_path.glob("m-shading.exr"))  # nothing decomposed again
    if op == "recolour":  # outside the mask: the 8-bit input
        a = load_image(d / "m.png").image
        outside = torch.ones(64, 80, dtype=torch.bool)
        outside[20:40, 20:60] = False
        assert float((a - res)[:, outside].abs().max()) < 0.02


def test_errors_one_line_and_no_overwrite(files, tmp_path, capsys):
    d, out = files
    base = ["edit", "recolour", str(d / "m.png"), "--from", str(out), "-o", str(tmp_path)]
    assert main(base) == 2  # no --mask
    assert "needs --mask" in capsys.readouterr().err
    assert main([*base, "--mask", str(d / "mask.png")]) == 0
    before = (tmp_path / "m-recolour.png").read_bytes()
    capsys.readouterr()
    assert main([*base, "--mask", str(d / "mask.png"), "--hue", "30"]) == 2
    err = capsys.readouterr().err
    assert "exists; pass --overwrite" in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "m-recolour.png").read_bytes() == before
    assert main([*base, "--mask", str(d / "mask.png"), "--hue", "30", "--overwrite"]) == 0
    assert (tmp_path / "m-recolour.png").read_bytes() != before
    # Stage 1 layers missing in a decompose-only folder
    only = tmp_path / "only"
    only.mkdir()
    for n in ("m-reflectance-linear16.png", "m-shading.exr"):
        (only / n).write_bytes((out / n).read_bytes())
    capsys.readouterr()
    args = ["edit", "merge", str(d / "m.png"), "--from", str(only), "-o", str(tmp_path / "x")]
    assert main(args) == 2
    assert "Stage 1" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert not np.any([p.name.startswith(".torchiid") for p in tmp_path.iterdir()])


def test_decompose_save_stage1_folder_serves_every_edit(files, tmp_path):
    d, _ = files
    dec = tmp_path / "dec"
    argv = ["decompose", str(d / "m.png"), "-o", str(dec), "--save-stage1", "--iterations", "1"]
    assert main([*argv, "--no-progress"]) == 0
    assert (dec / "m-sigma.exr").is_file() and (dec / "m-rho.exr").is_file()
    out = tmp_path / "edits"
    assert main(["edit", "merge", str(d / "m.png"), "--from", str(dec), "-o", str(out)]) == 0
    a = load_image(d / "m.png").image
    assert float((a - load_image(out / "m-merge.png").image).abs().max()) < 0.02
