import numpy as np
import pytest
import torch
from skimage import data, transform

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.features.proposals import (
    Proposals,
    linear_to_srgb,
    selective_search,
)
from torchiid.features.segmentation import graph_segmentation


@pytest.fixture(scope="module")
def astronaut():
    return transform.resize(data.astronaut(), (48, 64), anti_aliasing=True)  # sRGB floats


@pytest.fixture(scope="module")
def props(astronaut):
    return selective_search(astronaut, scales=(30, 60), max_proposals=None)


def _columns(p: Proposals) -> set[bytes]:
    return {np.packbits(c).tobytes() for c in p.membership.T.numpy()}


def test_masks_non_empty_and_cover(props):
    masks = props.masks()
    assert masks.shape == (props.num_proposals, 48, 64)
    assert masks.dtype == torch.bool
    assert bool(masks.flatten(1).any(1).all())
    assert bool(masks.any(0).all())
    assert torch.equal(masks.flatten(1).sum(1), props.areas)


def test_shapes_and_scores(props):
    a, p = props.num_atoms, props.num_proposals
    assert props.atom_labels.shape == (48, 64) and props.atom_labels.dtype == torch.long
    assert int(props.atom_labels.min()) == 0 and int(props.atom_labels.max()) == a - 1
    assert props.membership.shape == (a, p)
    assert props.scores.shape == (p,) and props.scores.dtype == torch.float32
    assert bool((props.scores > 0).all()) and float(props.scores[0]) == 1.0
    assert bool((props.scores[1:] < props.scores[:-1]).all())
    assert int(props.atom_sizes.sum()) == 48 * 64


def test_deduplicated(props):
    assert len(_columns(props)) == props.num_proposals
    full = props.masks().flatten(1).all(1)
    assert int(full.sum()) == 1  # every strategy reaches the whole image, kept once


@pytest.mark.parametrize("space", ["rgb", "hsv", "lab"])
@pytest.mark.parametrize("sim", ["ctsf", "tsf", "c"])
def test_hierarchy_per_strategy(astronaut, space, sim):
    p = selective_search(
        astronaut, scales=(40,), colour_spaces=(space,), similarities=(sim,), max_proposals=None
    )
    masks = p.masks()
    assert bool(masks.flatten(1).all(1).any()), "whole-image region missing"
    if space == "rgb":  # initial regions are Felzenszwalb's, hierarchy has 2R - 1 nodes
        seg = graph_segmentation(astronaut, scale=40, sigma=0.8, min_size=40)
        r = len(np.unique(seg))
        assert p.num_proposals == 2 * r - 1
        cols = _columns(p)
        for lab in np.unique(seg):
            region = torch.from_numpy(seg == lab)
            col = (
                region.reshape(-1).float()
                @ torch.nn.functional.one_hot(p.atom_labels.reshape(-1), p.num_atoms).float()
            ) > 0
            assert np.packbits(col.numpy()).tobytes() in cols
    # a hierarchy is laminar: two regions are nested or disjoint
    m = p.membership.double() * p.atom_sizes.double().unsqueeze(1)
    inter = p.membership.double().T @ m
    area = p.areas.double()
    nested = (inter == area.unsqueeze(0)) | (inter == area.unsqueeze(1)) | (inter == 0)
    assert bool(nested.all())


def test_boxes_match_masks(props):
    masks = props.masks()
    ys = torch.arange(48).view(1, -1, 1).expand_as(masks)
    xs = torch.arange(64).view(1, 1, -1).expand_as(masks)
    big = 10**6
    x0 = torch.where(masks, xs, big).flatten(1).amin(1)
    y0 = torch.where(masks, ys, big).flatten(1).amin(1)
    x1 = torch.where(masks, xs, -1).flatten(1).amax(1) + 1
    y1 = torch.where(masks, ys, -1).flatten(1).amax(1) + 1
    assert torch.equal(props.boxes, torch.stack([x0, y0, x1, y1], 1))


def test_deterministic_and_seeded(astronaut):
    kw = dict(scales=(30,), max_proposals=None)
    a = selective_search(astronaut, seed=3, **kw)
    b = selective_search(astronaut, seed=3, **kw)
    for f in ("atom_labels", "membership", "scores", "boxes", "strategy"):
        assert torch.equal(getattr(a, f), getattr(b, f))
    c = selective_search(astronaut, seed=4, **kw)
    assert _columns(a) == _columns(c)  # the same regions ...
    assert not torch.equal(a.membership, c.membership)  # ... ranked differently


def test_max_proposals(astronaut):
    full = selective_search(astronaut, scales=(30,), max_proposals=None)
    top = selective_search(astronaut, scales=(30,), max_proposals=25)
    assert top.num_proposals == 25
    assert torch.equal(top.membership, full.membership[:, :25])
    assert torch.equal(top.masks([3, 1]), full.masks()[[3, 1]])


def test_tensor_linear_input_and_batch(astronaut):
    srgb = astronaut
    lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    assert np.allclose(linear_to_srgb(lin), srgb, atol=1e-9)
    t = torch.from_numpy(lin).permute(2, 0, 1).float()
    kw = dict(scales=(30,), colour_spaces=("rgb",), max_proposals=None)
    single = selective_search(t, **kw)
    ref = selective_search(linear_to_srgb(t.double().permute(1, 2, 0).numpy()), **kw)
    assert torch.equal(single.membership, ref.membership)
    batch = selective_search(torch.stack([t, t.flip(-1)]), **kw)
    assert isinstance(batch, list) and len(batch) == 2
    assert torch.equal(batch[0].membership, single.membership)
    flipped = selective_search(t.flip(-1), **kw)
    assert torch.equal(batch[1].atom_labels, flipped.atom_labels)


def test_two_region_image():
    img = np.zeros((24, 32, 3))
    img[:, :16] = (0.9, 0.1, 0.1)
    img[:, 16:] = (0.1, 0.2, 0.9)
    p = selective_search(img, scales=(50,), colour_spaces=("rgb",), similarities=("ctsf",))
    masks = p.masks()
    assert p.num_proposals == 3
    left = torch.zeros(24, 32, dtype=torch.bool)
    left[:, :16] = True
    assert any(torch.equal(m, left) for m in masks)
    assert any(torch.equal(m, ~left) for m in masks)


def test_bad_input():
    with pytest.raises(ShapeError, match=r"\(3, H, W\) or \(B, 3, H, W\), got \(16, 16\)"):
        selective_search(torch.rand(16, 16))
    with pytest.raises(ShapeError, match=r"expected image of shape \(B, 3, H, W\)"):
        selective_search(torch.rand(4, 16, 16))
    with pytest.raises(ShapeError, match=r"shape \(H, W, 3\), got \(16, 16\)"):
        selective_search(np.zeros((16, 16)))
    with pytest.raises(ShapeError, match="dtype int32"):
        selective_search(np.zeros((16, 16, 3), dtype=np.int32))
    with pytest.raises(ShapeError, match="floating dtype"):
        selective_search(torch.zeros(3, 16, 16, dtype=torch.uint8))
    bad = torch.rand(3, 16, 16)
    bad[0, 2, 2] = float("nan")
    with pytest.raises(ImageError, match="1 NaN"):
        selective_search(bad)
    with pytest.raises(ImageError, match="NaN"):
        selective_search(np.full((16, 16, 3), np.nan))
    with pytest.raises(ImageError, match="16x4 px; at least 8"):
        selective_search(torch.rand(3, 4, 16))
    with pytest.raises(ImageError, match="9x5 px; at least 8"):
        selective_search(np.zeros((5, 9, 3), dtype=np.uint8))
    with pytest.raises(ShapeError, match="got list"):
        selective_search([[0.0]])


def test_bad_parameters():
    img = np.zeros((16, 16, 3))
    with pytest.raises(ParameterError, match="colour_spaces must be taken from"):
        selective_search(img, colour_spaces=("xyz",))
    with pytest.raises(ParameterError, match="letters 'ctsf'"):
        selective_search(img, similarities=("cq",))
    with pytest.raises(ParameterError, match="positive numbers"):
        selective_search(img, scales=())
    with pytest.raises(ParameterError, match="max_proposals"):
        selective_search(img, max_proposals=0)
    p = selective_search(img, scales=(10,))
    with pytest.raises(ParameterError, match=r"indices must lie in \[0, 1\)"):
        p.masks([1])


def test_segmentations_in_threads_give_the_one_thread_proposals():
    # with 2 threads the strategies' Felzenszwalb segmentations run at once; the proposals
    # (and their random ranking) are the same as on one thread
    img = torch.from_numpy(data.coffee()[::4, ::4].copy()).permute(2, 0, 1).float() / 255
    one = selective_search(img, seed=3)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        two = selective_search(img, seed=3)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one.atom_labels, two.atom_labels)
    assert torch.equal(one.membership, two.membership)
    assert torch.equal(one.boxes, two.boxes) and torch.equal(one.strategy, two.strategy)
