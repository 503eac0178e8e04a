"""``torchiid edit``: outputs, --from reuse, no-overwrite and one-line errors."""

import numpy as np
import pytest
import torch

from torchiid.cli import main
from torchiid.io import load_image, read_exr, save_image
from torchiid.synthetic import mondrian


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--hue", "nan", "argument --hue: not a finite number"),
        ("--strength", "inf", "argument --strength: not a finite number"),
        ("--blur", "1e9", "torchiid: error: --blur must be <= "),
        ("--feather", "-3", "torchiid: error: --feather must be >= 0"),
    ],
)
def test_numbers_out_of_range_are_usage_errors(files, tmp_path, capsys, option, value, message):
    d, out = files
    operation = {"--hue": "recolour", "--strength": "illumination-intensity"}.get(option, "merge")
    operation = "soften-shadows" if option == "--feather" else operation
    args = ["edit", operation, str(d / "m.png"), "--from", str(out), "-o", str(tmp_path / "x")]
    args += ["--mask", str(d / "mask.png"), f"{option}={value}"]
    if message.startswith("argument"):  # refused by the command line's parser
        with pytest.raises(SystemExit) as exited:
            main(args)
        assert exited.value.code == 2
    else:
        assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and "RuntimeWarning" not in err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["merge", "--blur", "1e9"], "--blur must be <= 80"),
        (["soften-shadows", "--mask", "MASK", "--feather", "-1"], "--feather must be >= 0"),
        (["illumination-intensity", "--strength", "-5"], "--strength must be >= 0"),
        (
            ["replace-albedo", "--mask", "MASK", "--texture", "TEX", "--scale", "1e5"],
            "--scale must be at most 40",
        ),
    ],
)
def test_numbers_are_checked_before_the_decomposition(
    files, tmp_path, capsys, monkeypatch, extra, message
):
    import torchiid.commands.edit as command

    d, _ = files
    monkeypatch.setattr(command, "_decompose", lambda *a: pytest.fail("decomposed first"))
    extra = [str(d / "mask.png") if x == "MASK" else str(d / "tex.png") if x == "TEX" else x
             for x in extra]  # fmt: skip
    args = ["edit", extra[0], str(d / "m.png"), "-o", str(tmp_path / "x"), *extra[1:]]
    assert main(args) == 2
    assert message in capsys.readouterr().err


def test_method_options_with_from_are_said_to_be_unused(files, tmp_path, capsys):
    d, out = files
    args = ["edit", "merge", str(d / "m.png"), "--from", str(out), "-o", str(tmp_path / "x")]
    assert main([*args, "--preset", "converged", "--iterations", "2"]) == 0
    err = capsys.readouterr().err
    assert "note: --preset, --iterations not used: --from reads the layers" in err
    assert main([*args, "--overwrite"]) == 0  # no method option: no note
    assert "not used" not in capsys.readouterr().err


def test_a_photo_the_decomposition_refuses_is_named(files, tmp_path, capsys):
    d, _ = files
    args = ["edit", "merge", str(d / "m.png"), "-o", str(tmp_path / "x"), "--memory-limit", "0.001"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"torchiid: error: {d / 'm.png'}: decomposing")
    assert "memory limit of 0.001 GB" in err[0]


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
                 "m-sigma.exr"]:  # fmt: skip
        assert (out / name).is_file(), name
    assert not (out / "m-rho.exr").exists()  # rho = I / sigma, rebuilt by --from
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
    # the Stage 1 shading missing (a folder of the retinex method, or of an older torchiid)
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


@pytest.fixture(scope="module")
def decomposed(files, tmp_path_factory):
    """A folder written by plain `torchiid decompose` (default options), and one with rho."""
    d, _ = files
    plain = tmp_path_factory.mktemp("plain")
    argv = ["decompose", str(d / "m.png"), "--iterations", "1", "--no-progress"]
    assert main([*argv, "-o", str(plain)]) == 0
    with_rho = tmp_path_factory.mktemp("with_rho")
    assert main([*argv, "-o", str(with_rho), "--save-stage1"]) == 0
    return plain, with_rho


EVERY_OPERATION = [
    ["merge"],
    ["illumination-colour", "--tint", "warm"],
    ["illumination-intensity"],
    ["illumination-intensity", "--no-merge"],
    ["remove-texture", "--mask", "mask.png"],
    ["replace-albedo", "--mask", "mask.png", "--texture", "tex.png"],
    ["recolour", "--mask", "mask.png", "--hue", "90"],
    ["soften-shadows", "--amount", "0.5"],
]


@pytest.mark.parametrize("argv", EVERY_OPERATION, ids=lambda a: " ".join(a[:2]))
def test_a_plain_decompose_folder_serves_every_edit(files, decomposed, tmp_path, argv):
    """`edit --from` a folder of `torchiid decompose`: the same result as with rho.exr there."""
    d, _ = files
    plain, with_rho = decomposed
    assert (plain / "m-sigma.exr").is_file() and not (plain / "m-rho.exr").exists()
    op, opts = argv[0], [str(d / a) if a.endswith(".png") else a for a in argv[1:]]
    results = []
    for folder in (plain, with_rho):
        out = tmp_path / folder.name
        base = ["edit", op, str(d / "m.png"), "--from", str(folder), "-o", str(out)]
        assert main([*base, *opts]) == 0
        assert not (out / "m-shading.exr").exists()  # nothing decomposed again
        results.append(read_exr(out / f"m-{op}.exr")[0])
    # rho rebuilt as I / sigma is the layer decompose returned, to float rounding
    np.testing.assert_allclose(results[0], results[1], rtol=1e-4, atol=1e-6)


def test_rho_rebuilt_from_sigma_is_the_decomposition_s(files, decomposed):
    from torchiid.commands.edit import _load_saved

    d, _ = files
    _, with_rho = decomposed
    image = load_image(d / "m.png").image
    saved = _load_saved(with_rho, d / "m.png", image, need_stage1=True)
    (with_rho / "m-rho.exr").rename(with_rho / "m-rho.exr.kept")
    try:
        rebuilt = _load_saved(with_rho, d / "m.png", image, need_stage1=True)
    finally:
        (with_rho / "m-rho.exr.kept").rename(with_rho / "m-rho.exr")
    torch.testing.assert_close(rebuilt[3], saved[3], rtol=1e-5, atol=1e-6)
    for a, b in zip(rebuilt[:3], saved[:3], strict=True):
        assert torch.equal(a, b)


def test_edit_records_its_version_and_decomposes_like_decompose(files):
    import json

    import torchiid

    d, out = files
    info = json.loads((out / "m-merge-info.json").read_text())
    assert info["torchiid_version"] == torchiid.__version__
    layers = json.loads((out / "m-info.json").read_text())
    assert layers["torchiid_version"] == torchiid.__version__ and "solves" in layers
    assert "m-sigma.exr" in layers["files"]


def test_negative_values_set_to_0_are_a_note_in_edit_too(tmp_path, capsys):
    linear = mondrian(64, 80, seed=3).image[0].permute(1, 2, 0).numpy().copy()
    linear[2, 3, 0] = -0.002  # a renderer's ringing
    np.save(tmp_path / "render.npy", linear)
    argv = ["edit", "merge", str(tmp_path / "render.npy"), "-o", str(tmp_path / "o")]
    assert main([*argv, "--iterations", "1"]) == 0
    err = capsys.readouterr().err
    assert (
        "torchiid: note: " in err
        and "render.npy: 1 negative value (down to -0.002) set to 0" in err
    )
    assert "InputWarning" not in err and "warnings.warn" not in err


def test_a_saved_decomposition_of_another_file_is_refused(files, decomposed, tmp_path, capsys):
    """The same name and size, another picture: the folder's -info.json tells them apart."""
    d, edit_out = files
    plain, _ = decomposed
    other = tmp_path / "in" / "m.png"
    other.parent.mkdir()
    save_image(other, load_image(d / "m.png").image.flip(-2), "srgb8")  # upside down
    for folder in (plain, edit_out):  # written by `decompose`, and by `edit` without --from
        args = ["edit", "merge", str(other), "--from", str(folder), "-o", str(tmp_path / "x")]
        assert main(args) == 2
        err = capsys.readouterr().err
        assert f"{folder}: its m-* layers are the decomposition of another file than {other}" in err
        assert f"(of {d / 'm.png'}, whose SHA-256 their m-info.json records)" in err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "x").exists()
    # the photo itself, copied elsewhere, is the same file: its decomposition serves it
    same = tmp_path / "copy" / "m.png"
    same.parent.mkdir()
    same.write_bytes((d / "m.png").read_bytes())
    args = ["edit", "merge", str(same), "--from", str(plain), "-o", str(tmp_path / "y")]
    assert main(args) == 0
