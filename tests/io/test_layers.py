"""torchiid.io.layers: the files of one decomposition, their optional extras and the preview."""

import json

import numpy as np
import pytest
import torch

from torchiid.io import ExtraOutputs, layer_file_names, load_image, read_exr, write_layers
from torchiid.io.layers import panel_size, preview_row


@pytest.fixture
def layers():
    g = torch.Generator().manual_seed(0)
    refl = 0.1 + 0.8 * torch.rand(3, 40, 56, generator=g)
    shading = 0.2 + torch.rand(1, 40, 56, generator=g)
    return refl * shading, refl, shading


def test_extras_add_the_npy_pair_and_the_confidence_picture(tmp_path, layers):
    image, refl, shading = layers
    conf = torch.zeros(1, 40, 56)
    conf[:, :, 28:] = 1.0
    extras = ExtraOutputs(npy=True, confidence=conf)
    files = write_layers(tmp_path, "p", *layers, shading_white=1.0, extras=extras)
    names = layer_file_names("p", save_npy=True, save_confidence=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        n for n in names if "params" not in n
    )
    assert set(files) == {n[2:] for n in names} - {"params.json"}
    np.testing.assert_array_equal(np.load(tmp_path / "p-reflectance.npy"), refl.permute(1, 2, 0))
    picture = load_image(tmp_path / "p-confidence.png", linear=True, min_side=1).image
    assert float(picture[:, :, :28].max()) == 0.0 and float(picture[:, :, 28:].min()) == 1.0
    described = json.loads((tmp_path / "p-info.json").read_text())["files"]
    assert "p-confidence.png" in described and "p-shading.npy" in described


def test_without_extras_only_the_standard_files(tmp_path, layers):
    write_layers(tmp_path, "p", *layers, shading_white=1.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        n for n in layer_file_names("p") if "params" not in n
    )


def test_the_exr_shading_rebuilds_the_image_from_the_16bit_reflectance(tmp_path, layers):
    image, _, _ = layers
    write_layers(tmp_path, "p", *layers, shading_white=1.0)
    r16 = load_image(tmp_path / "p-reflectance-linear16.png", linear=True, min_side=1).image
    s = torch.from_numpy(read_exr(tmp_path / "p-shading.exr")[0])
    rel = ((r16 * s - image).abs() / image).max()
    assert float(rel) < 2e-4  # the least-squares fit to the quantised reflectance


def test_the_extras_are_no_keywords_of_their_own(tmp_path, layers):
    # ExtraOutputs holds them
    with pytest.raises(TypeError, match="unexpected keyword argument 'save_npy'"):
        write_layers(tmp_path, "p", *layers, shading_white=1.0, save_npy=True)
    with pytest.raises(TypeError, match="unexpected keyword argument 'confidence'"):
        write_layers(tmp_path, "p", *layers, shading_white=1.0, confidence=torch.ones(1, 40, 56))
    assert not any(tmp_path.iterdir())


def test_preview_row_puts_panels_side_by_side_at_one_size():
    a = torch.zeros(3, 20, 30)
    b = torch.ones(1, 20, 30) * 0.5  # gray: repeated in R, G, B
    row = preview_row([a, b], (10, 15))
    assert row.shape == (3, 10, 15 + 4 + 15)
    assert float(row[:, :, :15].max()) == 0.0
    assert torch.equal(row[:, :, 15:19], torch.ones(3, 10, 4))  # the white separator
    torch.testing.assert_close(row[:, :, 19:], torch.full((3, 10, 15), 0.5))


def test_panel_size_never_enlarges():
    assert panel_size(300, 400, 1024) == (300, 400)
    assert panel_size(2000, 4000, 1024) == (512, 1024)
    assert panel_size(3, 4000, 640, minimum=2) == (2, 640)
