"""Reading a folder of decompositions for scoring (``torchiid.eval.results``)."""

import pytest
import torch

from torchiid.core.exceptions import ParameterError, TorchiidError
from torchiid.eval import load_layer
from torchiid.io import save_image


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


def test_a_channels_first_npy_is_named_with_the_shape_expected(tmp_path):
    import numpy as np

    from torchiid.core.exceptions import ImageError

    np.save(tmp_path / "a-reflectance.npy", np.random.rand(3, 12, 10).astype(np.float32))
    with pytest.raises(ImageError) as err:
        load_layer(tmp_path, "a", "reflectance")
    message = str(err.value)
    assert "a-reflectance.npy" in message and "(3, 12, 10)" in message
    assert "expected (H, W) or (H, W, 3)" in message and "10 channels" not in message
    np.save(tmp_path / "a-shading.npy", np.random.rand(1, 12, 10).astype(np.float32))
    with pytest.raises(ImageError, match=r"\(1, 12, 10\); expected \(H, W\) or \(H, W, 3\)"):
        load_layer(tmp_path, "a", "shading")
    # channels last is read
    np.save(tmp_path / "a-reflectance.npy", np.random.rand(12, 10, 3).astype(np.float32))
    assert load_layer(tmp_path, "a", "reflectance").shape == (1, 3, 12, 10)


def test_a_folder_without_any_layer_is_one_error_naming_the_files(tmp_path):
    from torchiid.eval.results import check_results_folder

    (tmp_path / "diffuse-reflectance.npy").write_bytes(b"")
    with pytest.raises(TorchiidError) as err:
        check_results_folder(tmp_path, ["apple", "box"], "MIT object name")
    message = str(err.value)
    assert message.startswith(f"{tmp_path}: no layers of any of the 2 image(s)")
    for name in ("<id>-reflectance.npy", "<id>-shading.exr", "<id>-reflectance.png"):
        assert name in message
    assert "MIT object name (e.g. apple-reflectance.npy)" in message
    assert "it holds diffuse-reflectance.npy" in message
    save_image(tmp_path / "box-shading.png", torch.zeros(1, 6, 7), "srgb8")
    check_results_folder(tmp_path, ["apple", "box"])  # one image has a layer: each is its own


def test_input_decoding_names_layers_of_the_wrongly_decoded_input():
    from torchiid.eval.results import input_decoding
    from torchiid.io import linear_to_srgb, srgb_to_linear

    gen = torch.Generator().manual_seed(5)
    image = torch.rand(3, 32, 32, generator=gen) * 0.8 + 0.05  # linear
    mask = torch.ones(1, 32, 32, dtype=torch.bool)
    mask[:, :4] = False
    shading = torch.rand(1, 1, 32, 32, generator=gen) * 0.5 + 0.5

    def layers(product):
        return product / shading, 3 * shading  # any global scale

    assert input_decoding(image, *layers(image[None]), mask) is None
    assert input_decoding(image, *layers(srgb_to_linear(image)[None]), mask) == "srgb"
    assert input_decoding(image, *layers(linear_to_srgb(image)[None]), mask) == "linear"
    # layers that do not multiply to any input: no claim
    other = torch.rand(1, 3, 32, 32, generator=gen) + 0.1
    assert input_decoding(image, other, shading, mask) is None
    # an image whose decodings differ only by a scale cannot tell
    flat = torch.full((3, 32, 32), 0.4)
    assert input_decoding(flat, *layers(srgb_to_linear(flat)[None]), mask) is None
