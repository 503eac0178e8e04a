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
