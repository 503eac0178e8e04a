import math

import pytest
import torch
import torch.nn.functional as F
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb
from skimage import data

from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.features import patches as patches_mod
from torchiid.features.backbone import FeatureMapExtractor, efficientnet_lite0, feature_offset
from torchiid.features.onnx_backend import OnnxFeatureExtractor
from torchiid.features.patches import (
    PatchFeatureExtractor,
    patch_features,
    patch_grid,
)


@pytest.fixture(scope="module")
def onnx_extractor(onnx_path):
    return OnnxFeatureExtractor(onnx_path)


@pytest.fixture(scope="module")
def image():
    """Two small linear-RGB crops of skimage's coffee photo, (2, 3, 64, 96)."""
    srgb = torch.from_numpy(data.coffee()).permute(2, 0, 1)[None].float() / 255
    srgb = F.interpolate(srgb, size=(128, 192), mode="bilinear", antialias=True)
    return rgb_to_linear_rgb(torch.cat([srgb[..., :64, :96], srgb[..., 64:, 96:]]))


# ---------------------------------------------------------------- grid


@pytest.mark.parametrize(("h", "w"), [(60, 60), (61, 119), (100, 130), (384, 512), (90, 150)])
def test_grid_covers_image(h, w):
    g = patch_grid(h, w)
    cover = torch.zeros(h, w, dtype=torch.long)
    for x1, y1, x2, y2 in g.boxes.tolist():
        assert 0 <= x1 < x2 <= w and 0 <= y1 < y2 <= h and x2 - x1 == 60 and y2 - y1 == 60
        cover[y1:y2, x1:x2] += 1
    assert cover.min() >= 1
    assert len(g) == g.shape[0] * g.shape[1]
    assert g.centers.dtype == torch.long
    torch.testing.assert_close(g.centers, g.boxes[:, [1, 0]] + 30)
    ys = g.boxes[:: g.shape[1], 1]
    assert ys.diff().le(30).all() and ys.diff().gt(0).all() and ys[0] == 0 and ys[-1] == h - 60
    assert g.shape == (math.ceil((h - 60) / 30) + 1, math.ceil((w - 60) / 30) + 1)


def test_grid_errors():
    with pytest.raises(ParameterError, match="smaller than a 60 px patch"):
        patch_grid(59, 100)
    with pytest.raises(ParameterError, match="must be >= 1"):
        patch_grid(100, 100, stride=0)


# ---------------------------------------------------------------- patch features


def test_shared_mode_pools_at_patch_positions(image):
    # A fake feature map holding each cell's centre (original-image coordinates): RoI-align of
    # a linear function is exact, so every interior patch must pool to its box centre.
    scale = 2.0

    def coords(x):
        hs, ws = x.shape[-2:]
        fy = (32 * torch.arange(-(-hs // 32)) + feature_offset(hs) + 0.5) / (hs / 64)
        fx = (32 * torch.arange(-(-ws // 32)) + feature_offset(ws) + 0.5) / (ws / 96)
        return torch.stack(torch.broadcast_tensors(fy[:, None], fx[None, :]))[None]

    grid = patch_grid(64, 96, size=20, stride=10)
    pooled = patches_mod._shared(image[:1], grid, coords, scale)[0]  # (N, 2): (y, x)
    centre = grid.boxes.double().view(-1, 2, 2).mean(1)[:, [1, 0]].float()
    inner = (grid.boxes[:, 0] >= 16) & (grid.boxes[:, 2] <= 96 - 16)
    inner &= (grid.boxes[:, 1] >= 16) & (grid.boxes[:, 3] <= 64 - 16)
    assert inner.sum() >= 4
    torch.testing.assert_close(pooled[inner], centre[inner], atol=1e-4, rtol=0)


def test_shapes_batch_determinism_and_backends(image, onnx_extractor):
    out = patch_features(image, backend="onnx", onnx_extractor=onnx_extractor)
    assert out.features.shape == (2, 6, 1280) and out.grid.shape == (2, 3)
    assert out.mode == "shared" and out.features.dtype == torch.float32
    again = patch_features(image, backend="onnx", onnx_extractor=onnx_extractor)
    torch.testing.assert_close(out.features, again.features, atol=0, rtol=0)
    single = patch_features(image[1:], backend="onnx", onnx_extractor=onnx_extractor)
    torch.testing.assert_close(single.features[0], out.features[1], atol=1e-5, rtol=1e-5)
    torch_out = patch_features(image, backend="torch")
    assert (torch_out.features - out.features).abs().max() < 1e-4
    # Different patches of different images differ.
    assert (out.features[0, 0] - out.features[1, 0]).abs().max() > 0.1


def test_onnx_batch_runs_one_image_at_a_time_and_releases_the_arena_once(image, onnx_path):
    calls = []

    class Recording(OnnxFeatureExtractor):
        def __call__(self, x, *, release_memory=True):
            calls.append((x.shape[0], release_memory))
            return super().__call__(x, release_memory=release_memory)

    extractor = Recording(onnx_path)
    batch = patch_features(image, onnx_extractor=extractor)
    assert calls == [(1, False), (1, True)]
    alone = [patch_features(image[i : i + 1], onnx_extractor=extractor) for i in range(2)]
    expected = torch.cat([a.features for a in alone])
    torch.testing.assert_close(batch.features, expected, atol=0, rtol=0)


def test_released_extractors_are_loaded_again_with_the_same_features(image, onnx_path, monkeypatch):
    from torchiid.features import onnx_backend

    monkeypatch.setattr(onnx_backend, "ensure_onnx_model", lambda cache_dir=None: onnx_path)
    patches_mod.release_feature_extractors()
    first = patch_features(image)  # the default extractor, kept for the next call
    kept = (patches_mod._default_onnx, onnx_backend._session, patches_mod._torch_extractor)
    assert [c.cache_info().currsize for c in kept[:2]] == [1, 1]
    patch_features(image, backend="torch")
    assert kept[2].cache_info().currsize == 1
    patches_mod.release_feature_extractors()
    assert [c.cache_info().currsize for c in kept] == [0, 0, 0]
    again = patch_features(image)
    torch.testing.assert_close(again.features, first.features, atol=0, rtol=0)


def test_crop_mode_matches_direct_computation(image, onnx_extractor):
    image = image[..., :60, :90]  # two patches per image
    grid = patch_grid(60, 90)
    out = patch_features(image, mode="crop", backend="torch", batch_size=3)
    srgb = torch.where(
        image <= 0.0031308, 12.92 * image, 1.055 * image.clamp_min(1e-12) ** (1 / 2.4) - 0.055
    )
    model = FeatureMapExtractor(efficientnet_lite0()).eval()
    for n, (x1, y1, x2, y2) in enumerate(grid.boxes.tolist()):
        crop = F.interpolate(srgb[:, :, y1:y2, x1:x2], size=(224, 224), mode="bilinear")
        with torch.no_grad():
            ref = model(crop).mean(dim=(2, 3))
        torch.testing.assert_close(out.features[:, n], ref, atol=1e-4, rtol=1e-4)
    onnx_out = patch_features(image, mode="crop", onnx_extractor=onnx_extractor)
    assert (onnx_out.features - out.features).abs().max() < 1e-4


def test_dtype_follows_input(image, onnx_extractor):
    out = patch_features(image.double(), onnx_extractor=onnx_extractor)
    assert out.features.dtype == torch.float64 and out.features.device == image.device


def test_linear_to_srgb_matches_kornia_and_has_finite_gradient():
    x = torch.linspace(0, 1, 101, dtype=torch.float64).requires_grad_(True)
    y = linear_to_srgb(x)
    ref = linear_rgb_to_rgb(x.detach().expand(3, -1)[None, :, :, None])[0, 0, :, 0]
    torch.testing.assert_close(y, ref)
    y.sum().backward()
    assert torch.isfinite(x.grad).all()


def test_module_equals_function(image):
    module = PatchFeatureExtractor().train()
    assert not module.extractor.training
    with torch.no_grad():
        out = module(image)
    torch.testing.assert_close(out.features, patch_features(image, backend="torch").features)


@pytest.mark.parametrize(
    ("bad", "error", "match"),
    [
        (torch.rand(1, 4, 64, 64), ShapeError, r"expected image of shape \(B, 3, H, W\)"),
        (torch.rand(3, 64, 64), ShapeError, r"expected image of shape \(B, 3, H, W\)"),
        (torch.full((1, 3, 64, 64), float("nan")), ImageError, "contains 12288 NaN"),
        (torch.rand(1, 3, 50, 80), ImageError, "80x50 px; at least 60 px"),
        (-torch.rand(1, 3, 64, 64), ImageError, "negative values"),
    ],
)
def test_bad_images(bad, error, match):
    with pytest.raises(error, match=match):
        patch_features(bad, backend="torch")


def test_bad_parameters(image):
    with pytest.raises(ParameterError, match="mode must be 'shared' or 'crop', got 'dense'"):
        patch_features(image, mode="dense")
    with pytest.raises(ParameterError, match="backend must be 'onnx' or 'torch', got 'tf'"):
        patch_features(image, backend="tf")
    with pytest.raises(ParameterError, match="scale must be > 0"):
        patch_features(image, scale=0.0)
