"""``torchiid edit``: what each operation does to the picture, on a decomposition with known
layers (a Mondrian written as the files of ``torchiid decompose``, reused with ``--from``)."""

import numpy as np
import pytest
import torch

from torchiid.cli import main
from torchiid.edit import gaussian, linear_to_lab
from torchiid.io import load_image, read_exr, save_image
from torchiid.synthetic import mondrian

H, W = 64, 80
BOX = (slice(20, 40), slice(20, 60))


def _exr(path):
    arr = torch.from_numpy(np.ascontiguousarray(read_exr(path)[0]))
    return arr[None] if arr.dim() == 2 else arr.permute(2, 0, 1)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """The input photo, its known layers and a folder holding them as `decompose` writes them."""
    d = tmp_path_factory.mktemp("effects")
    syn = mondrian(H, W, seed=2)
    r, s = syn.reflectance[0], syn.shading[0]
    sigma = gaussian(syn.shading, 3.0)[0]  # a smoother Stage 1 shading
    rho = (syn.image[0] / sigma).clamp(0, 1)
    dec = d / "dec"
    save_image(dec / "m-reflectance-linear16.png", r, "linear16")
    save_image(dec / "m-shading.exr", s, "exr")
    save_image(dec / "m-sigma.exr", sigma, "exr")
    save_image(dec / "m-rho.exr", rho, "exr")
    save_image(d / "m.png", syn.image[0], "srgb16")
    box = torch.zeros(1, H, W)
    box[:, BOX[0], BOX[1]] = 1
    save_image(d / "mask.png", box, "srgb8")
    tex = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0))
    save_image(d / "tex.png", tex, "srgb16")
    image = load_image(d / "m.png").image
    r16 = load_image(dec / "m-reflectance-linear16.png", linear=True).image
    layers = {"r": r16, "s": _exr(dec / "m-shading.exr"), "sigma": sigma, "rho": rho}
    return d, image, layers, box.bool()


def _edit(saved, tmp_path, op, *options):
    d = saved[0]
    opts = [str(d / o) if o.endswith(".png") else o for o in options]
    argv = ["edit", op, str(d / "m.png"), "--from", str(d / "dec"), "-o", str(tmp_path), *opts]
    assert main(argv) == 0
    return tmp_path / f"m-{op}"


def test_merge_rebuilds_the_picture_with_a_shading_between_the_stages(saved, tmp_path):
    _, image, layers, _ = saved
    tag = _edit(saved, tmp_path, "merge")
    r, s = _exr(f"{tag}-reflectance.exr"), _exr(f"{tag}-shading.exr")
    torch.testing.assert_close(r * s, image, atol=1e-4, rtol=1e-3)
    lo = torch.minimum(layers["s"], layers["sigma"])
    hi = torch.maximum(layers["s"], layers["sigma"])
    assert bool(((s[:1] >= lo - 1e-3) & (s[:1] <= hi + 1e-3)).all())
    torch.testing.assert_close(_exr(f"{tag}.exr"), image, atol=1e-4, rtol=1e-3)


def test_illumination_colour_tints_the_lit_areas(saved, tmp_path):
    _, image, layers, _ = saved
    result = _exr(f"{_edit(saved, tmp_path, 'illumination-colour', '--tint', 'green')}.exr")
    y = layers["s"][0]
    lit = y >= torch.quantile(y.flatten(), 0.95)

    def green_share(x):
        return (x[1] / x.sum(0).clamp_min(1e-6))[lit].mean()

    assert float(green_share(result)) > float(green_share(image)) + 0.05
    # farther than the fall-off radius (35% of 80 px) from every lit pixel: unchanged
    ys, xs = torch.nonzero(lit, as_tuple=True)
    gy, gx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    d2 = (gy[..., None] - ys).square() + (gx[..., None] - xs).square()
    far = d2.amin(-1).float().sqrt() > 0.35 * W + 1
    assert int(far.sum()) > 100
    torch.testing.assert_close(result[:, far], image[:, far], atol=2e-3, rtol=1e-2)


def test_illumination_intensity_brightens_the_dark_and_keeps_the_bright(saved, tmp_path):
    _, image, layers, _ = saved
    result = _exr(f"{_edit(saved, tmp_path, 'illumination-intensity')}.exr")
    y = layers["s"][0]
    dark, bright = y <= torch.quantile(y.flatten(), 0.1), y >= torch.quantile(y.flatten(), 0.99)
    gain = result.sum(0) / image.sum(0)
    assert float(gain[dark].mean()) > 1.05
    assert float((gain[bright] - 1).abs().max()) < 0.03


def test_recolour_turns_the_hue_inside_the_mask_only(saved, tmp_path):
    _, image, layers, box = saved
    tag = _edit(saved, tmp_path, "recolour", "--mask", "mask.png", "--hue", "90")
    result, r_new = _exr(f"{tag}.exr"), _exr(f"{tag}-reflectance.exr")
    torch.testing.assert_close(result[:, ~box[0]], image[:, ~box[0]], atol=1e-3, rtol=1e-3)
    lab0, lab1 = linear_to_lab(layers["r"][None])[0], linear_to_lab(r_new[None])[0]
    inside = box[0] & (torch.hypot(lab0[1], lab0[2]) > 10)  # coloured pixels
    inside &= ((r_new > 0) & (r_new < 1)).all(0)  # not gamut-clipped
    turn = torch.rad2deg(torch.atan2(lab1[2], lab1[1]) - torch.atan2(lab0[2], lab0[1])) % 360
    assert int(inside.sum()) > 50
    assert float((turn[inside] - 90).abs().median()) < 5


def test_soften_shadows_raises_the_dark_shading(saved, tmp_path):
    _, image, layers, _ = saved
    tag = _edit(saved, tmp_path, "soften-shadows", "--amount", "0.5", "--no-merge")
    s_new, s = _exr(f"{tag}-shading.exr")[:1], layers["s"]
    dark = s <= torch.quantile(s.flatten(), 0.1)
    assert float((s_new / s)[dark].mean()) > 1.2
    span = lambda x: float(x.log().amax() - x.log().amin())  # noqa: E731
    assert span(s_new) < 0.6 * span(s)


def test_replace_albedo_carries_the_texture_under_the_shading(saved, tmp_path):
    d, image, _, box = saved
    tag = _edit(saved, tmp_path, "replace-albedo", "--mask", "mask.png", "--texture", "tex.png")
    r_new = _exr(f"{tag}-reflectance.exr")
    tex = load_image(d / "tex.png", min_side=1).image
    tiles = tex.repeat(1, 3, 5)[:, :20, :40]  # from the box's top-left corner
    torch.testing.assert_close(r_new[:, BOX[0], BOX[1]], tiles, atol=1e-4, rtol=1e-4)
    result = _exr(f"{tag}.exr")
    torch.testing.assert_close(result[:, ~box[0]], image[:, ~box[0]], atol=1e-3, rtol=1e-3)


def test_remove_texture_leaves_one_flat_colour_in_the_mask(saved, tmp_path):
    _, image, layers, box = saved
    tag = _edit(saved, tmp_path, "remove-texture", "--mask", "mask.png", "--no-merge")
    r_new = _exr(f"{tag}-reflectance.exr")
    inside = r_new[:, box[0]]
    assert float(inside.std(1).max()) < 1e-6
    assert float((layers["r"][:, box[0]].std(1)).max()) > 0.05  # there was texture before
    assert torch.equal(r_new[:, ~box[0]], layers["r"][:, ~box[0]])
