import pytest
import torch
from skimage import data

from torchiid.core.exceptions import ModelError, ShapeError
from torchiid.features import backbone
from torchiid.features.backbone import (
    EfficientNetLite0,
    _Conv2dSame,
    efficientnet_lite0,
    feature_offset,
    normalize,
    preprocess,
    weights_path,
)


@pytest.fixture(scope="module")
def model():
    return efficientnet_lite0(pretrained=True)


def _srgb(name):
    return torch.from_numpy(getattr(data, name)()).permute(2, 0, 1)[None].float() / 255


def test_weights_load_strictly_and_cover_every_key(model):
    state = torch.load(weights_path(), weights_only=True, map_location="cpu")
    assert set(state) == set(model.state_dict())
    assert not model.training


def test_classifies_skimage_photos(model):
    batch = torch.cat([preprocess(_srgb("chelsea")), preprocess(_srgb("coffee"))])
    with torch.no_grad():
        cat, coffee = model(batch).argmax(-1).tolist()
    assert cat in range(281, 286)  # ImageNet cats
    assert cat == 285  # Egyptian cat, as DESIGN.md records
    assert coffee == 967  # espresso


@pytest.mark.parametrize("hw", [(64, 96), (77, 101), (33, 65)])
def test_forward_features_shape_and_range(model, hw):
    x = normalize(torch.rand(2, 3, *hw, generator=torch.Generator().manual_seed(0)))
    with torch.no_grad():
        f = model.forward_features(x)
    assert f.shape == (2, 1280, -(-hw[0] // 32), -(-hw[1] // 32))
    assert f.min() >= 0 and f.max() <= 6


def test_logits_are_fc_of_pooled_features(model):
    x = normalize(torch.rand(1, 3, 96, 64, generator=torch.Generator().manual_seed(1)))
    with torch.no_grad():
        ref = model._fc(model.forward_features(x).mean(dim=(2, 3)))
        torch.testing.assert_close(model(x), ref)


def test_normalize_maps_range():
    x = torch.tensor([0.0, 127 / 255, 1.0], dtype=torch.float64)
    torch.testing.assert_close(
        normalize(x), torch.tensor([-127 / 128, 0.0, 1.0], dtype=torch.float64)
    )


@pytest.mark.parametrize("length", [224, 225, 97, 130, 61, 768, 1000])
def test_feature_offset_matches_delta_conv_chain(length):
    # Five stride-2 "SAME" convolutions with a centred delta kernel pick input 32 f + offset.
    x = torch.arange(length, dtype=torch.float64).reshape(1, 1, 1, length).repeat(1, 1, 3, 1)
    for k in (3, 3, 5, 3, 5):
        conv = _Conv2dSame(1, 1, k, stride=2).double()
        with torch.no_grad():
            conv.weight.zero_()
            conv.weight[0, 0, k // 2, k // 2] = 1
            x = conv(x)
    f = torch.arange(x.shape[-1], dtype=torch.float64)
    torch.testing.assert_close(x[0, 0, 0], 32 * f + feature_offset(length))


def test_same_padding_matches_tensorflow_rule():
    # TF SAME, stride 2: total pad max((ceil(L/2) - 1) * 2 + k - L, 0), extra pixel at the end.
    gen = torch.Generator().manual_seed(2)
    for length in (8, 9):
        for k in (3, 5):
            conv = _Conv2dSame(2, 3, k, stride=2).double()
            x = torch.rand(1, 2, length, length + 1, dtype=torch.float64, generator=gen)
            pads = []
            for n in (length + 1, length):
                total = max((-(-n // 2) - 1) * 2 + k - n, 0)
                pads += [total // 2, total - total // 2]
            ref = torch.nn.functional.conv2d(
                torch.nn.functional.pad(x, pads), conv.weight, stride=2
            )
            torch.testing.assert_close(conv(x), ref)


def test_preprocess_shape_and_error():
    assert preprocess(torch.rand(2, 3, 50, 70)).shape == (2, 3, 224, 224)
    with pytest.raises(ShapeError, match=r"expected image of shape \(B, 3, H, W\)"):
        preprocess(torch.rand(3, 50, 70))


def test_corrupt_weights_raise_model_error(tmp_path, monkeypatch):
    bad = tmp_path / "bad.pth"
    torch.save({"_conv_stem.weight": torch.zeros(1)}, bad)
    monkeypatch.setattr(backbone, "weights_path", lambda: bad)
    with pytest.raises(ModelError, match="cannot load backbone weights"):
        efficientnet_lite0(pretrained=True)
    assert isinstance(efficientnet_lite0(pretrained=False), EfficientNetLite0)
