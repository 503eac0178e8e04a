import numpy as np
import pytest
import torch
from skimage import data, transform

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.features.midlevel import midlevel_features
from torchiid.features.proposals import selective_search
from torchiid.features.visualize import (
    draw_patch_grid,
    overlay_masks,
    pca_image,
    select_masks,
    to_uint8_image,
)

H, W = 36, 48


@pytest.fixture(scope="module")
def photo():
    return transform.resize(data.coffee(), (H, W), anti_aliasing=True)


@pytest.fixture(scope="module")
def props(photo):
    return selective_search(photo, scales=(30,), max_proposals=60)


def test_to_uint8_image(photo):
    u = to_uint8_image(photo)
    assert u.shape == (H, W, 3) and u.dtype == np.uint8
    np.testing.assert_array_equal(u, np.round(photo * 255).astype(np.uint8))
    t = torch.from_numpy(photo).permute(2, 0, 1).unsqueeze(0)
    np.testing.assert_array_equal(to_uint8_image(t), u)
    with pytest.raises(ShapeError, match=r"\(3, H, W\) or \(1, 3, H, W\), got \(2, 3, 4, 4\)"):
        to_uint8_image(torch.zeros(2, 3, 4, 4))
    with pytest.raises(ImageError, match="NaN"):
        to_uint8_image(np.full((4, 4, 3), np.nan))


def test_pca_image(props):
    mid = midlevel_features(props)
    img = pca_image(mid)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    assert img.reshape(-1, 3).min(0).tolist() == [0, 0, 0]
    assert img.reshape(-1, 3).max(0).tolist() == [255, 255, 255]
    # the same picture from the reduced tensor; channel order follows the components
    np.testing.assert_array_equal(pca_image(mid.pca(5)), img)
    z = mid.pca(3)[0, 0]
    order = torch.argsort(z.flatten())
    assert img[..., 0].reshape(-1)[order.numpy()][0] == 0
    with pytest.raises(ShapeError, match="got \\(4, 4\\)"):
        pca_image(torch.zeros(4, 4))


def test_overlay_masks(photo, props):
    masks = props.masks([0, 5, 10])
    out = overlay_masks(photo, masks, alpha=0.5, columns=2, contour=False)
    assert out.shape == (2 * H, 2 * W, 3) and out.dtype == np.uint8
    base = to_uint8_image(photo)
    tile = out[:H, W:]  # second mask
    inside = masks[1].numpy()
    np.testing.assert_array_equal(tile[~inside], base[~inside])
    if inside.any():
        assert (tile[inside] != base[inside]).any()
    assert (out[H:, W:] == 0).all()  # unused tile
    row = overlay_masks(photo, masks)
    assert row.shape == (H, 3 * W, 3)
    with pytest.raises(ShapeError, match=f"expected masks of shape \\(N, {H}, {W}\\)"):
        overlay_masks(photo, torch.zeros(2, H, W + 1, dtype=torch.bool))
    with pytest.raises(ParameterError, match="alpha"):
        overlay_masks(photo, masks, alpha=2.0)


def test_draw_patch_grid(photo):
    boxes = torch.tensor([[0, 0, 20, 20], [10, 5, 30, 25]])
    out = draw_patch_grid(photo, boxes, colour=(255, 0, 255))
    assert out.shape == (H, W, 3) and out.dtype == np.uint8
    assert out[5, 10:30].tolist() == [[255, 0, 255]] * 20  # top edge of the second box
    assert out[24, 29].tolist() == [255, 0, 255]  # bottom-right corner (x1, y1 exclusive)
    base = to_uint8_image(photo)
    np.testing.assert_array_equal(out[30:, 35:], base[30:, 35:])
    assert out[14, 19].tolist() == [255, 0, 255]  # centre dot of the second box
    centres = np.array([[10.0, 10.0], [20.0, 30.0]])
    dots = draw_patch_grid(photo, centres, colour=(0, 255, 0), radius=1)
    assert dots[20, 30].tolist() == [0, 255, 0] and dots[10, 10].tolist() == [0, 255, 0]
    with pytest.raises(ShapeError, match=r"\(N, 4\) or centres \(N, 2\), got shape \(2, 3\)"):
        draw_patch_grid(photo, np.zeros((2, 3)))


def test_select_masks(props):
    idx = select_masks(props, n=3, min_area=0.05, max_area=0.7, max_iou=0.3)
    assert idx.dtype == torch.long and len(set(idx.tolist())) == len(idx) == 3
    masks = props.masks(idx)
    frac = masks.flatten(1).double().mean(1)
    qualifying = (
        (props.areas.double() / (H * W) >= 0.05) & (props.areas.double() / (H * W) <= 0.7)
    ).sum()
    if int(qualifying) >= 3:
        assert bool(((frac >= 0.05) & (frac <= 0.7))[:1].all())
    for i in range(len(idx)):
        for j in range(i):
            inter = (masks[i] & masks[j]).sum()
            union = (masks[i] | masks[j]).sum()
            if bool(((frac >= 0.05) & (frac <= 0.7))[[i, j]].all()):
                assert float(inter / union) <= 0.3 + 1e-12
    with pytest.raises(ParameterError, match="n must be >= 1"):
        select_masks(props, n=0)
