import math
from pathlib import Path

import pytest
import torch

from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ImageError, ParameterError
from torchiid.eval.video import pair_warping_error, read_flo, warping_error, write_flo
from torchiid.synthetic import moving_mondrian
from torchiid.video import estimate_flow, occlusion_mask, resize_flow, warp


def textured(h=72, w=96, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, h // 4, w // 4, generator=g)
    return torch.nn.functional.interpolate(x, size=(h, w), mode="bilinear")[0] * 0.8 + 0.1


def test_warp_integer_shift_and_inside():
    img = torch.arange(4 * 6, dtype=torch.float32).view(1, 1, 4, 6)
    flow = torch.zeros(1, 2, 4, 6)
    flow[:, 0] = 2.0  # out(p) = img(p + 2 px in x)
    out, inside = warp(img, flow)
    assert torch.equal(out[..., :4], img[..., 2:])
    assert inside[0, 0, 0].tolist() == [True] * 4 + [False] * 2
    lab, _ = warp(img, flow, mode="nearest")
    assert torch.equal(lab[..., :4], img[..., 2:])


def test_occlusion_mask_detects_disagreeing_flows():
    fw = torch.zeros(1, 2, 20, 20)
    bw = torch.zeros(1, 2, 20, 20)
    assert bool(occlusion_mask(fw, bw).all())
    bw[..., 5:10, 5:10] = 3.0  # the backward flow disagrees in a block
    m = occlusion_mask(fw, bw)
    assert not bool(m[..., 5:10, 5:10].any()) and bool(m[..., 12:, 12:].all())


def test_resize_flow_scales_vectors():
    f = torch.ones(1, 2, 10, 20)
    f[:, 1] = -2
    g = resize_flow(f, (20, 40))
    assert g.shape == (1, 2, 20, 40)
    assert torch.allclose(g[:, 0], torch.full((1, 20, 40), 2.0))
    assert torch.allclose(g[:, 1], torch.full((1, 20, 40), -4.0))


@pytest.mark.parametrize("method", ["dis", "farneback"])
def test_estimate_flow_recovers_a_translation(method):
    a = textured()
    b = torch.roll(a, shifts=(1, 3), dims=(1, 2))  # content moves 3 px right, 1 px down
    f = estimate_flow(a, b, method)
    inner = f[0, :, 12:-12, 12:-12]
    assert abs(float(inner[0].median()) - 3) < 0.3
    assert abs(float(inner[1].median()) - 1) < 0.3
    with pytest.raises(ParameterError):
        estimate_flow(a, b, "lucas-kanade")


def test_flo_round_trip_and_bad_files(tmp_path):
    f = torch.randn(1, 2, 7, 9)
    path = write_flo(tmp_path / "a.flo", f)
    assert torch.equal(read_flo(path), f)
    # Middlebury layout: tag, width, height
    raw = path.read_bytes()
    assert raw[:4] == b"PIEH" and int.from_bytes(raw[4:8], "little") == 9
    (tmp_path / "bad.flo").write_bytes(b"XXXX" + raw[4:])
    with pytest.raises(ImageError, match="bad.flo: not a Middlebury"):
        read_flo(tmp_path / "bad.flo")
    (tmp_path / "short.flo").write_bytes(raw[:40])
    with pytest.raises(ImageError, match="truncated"):
        read_flo(tmp_path / "short.flo")
    with pytest.raises(ImageError, match="missing.flo"):
        read_flo(tmp_path / "missing.flo")


SINTEL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "sintel-clean"
SINTEL_FLO = SINTEL / "alley_1" / "gt" / "frame_0002.flo"


@pytest.mark.skipif(not SINTEL_FLO.is_file(), reason="shared Sintel sample not present")
def test_read_flo_of_a_real_sintel_file():
    # a file written by Sintel's own tools, not by write_flo: 1024x436, the PIEH tag
    raw = SINTEL_FLO.read_bytes()
    assert raw[:4] == b"PIEH" and len(raw) == 12 + 8 * 1024 * 436
    f = read_flo(SINTEL_FLO)
    assert f.shape == (1, 2, 436, 1024) and f.dtype == torch.float32
    assert bool(torch.isfinite(f).all())
    # pixels, plausible for a 1024 px frame, and alley_1 moves: not an all-zero field
    assert 0.1 < float(f.abs().median()) < 1024
    # the frames it belongs to have its size
    from torchiid.io import load_image

    assert load_image(SINTEL / "alley_1" / "frame_0002.png").image.shape[-2:] == (436, 1024)


def test_warping_error_of_the_true_layers_is_zero():
    seq = moving_mondrian(48, 64, frames=3, velocity=(2, 1))
    flows = [seq.flow[t : t + 1] for t in range(2)]
    occl = [~seq.valid[t : t + 1] for t in range(2)]
    truth = warping_error(list(seq.reflectance), flows=flows, occlusions=occl)
    assert truth.mean < 1e-10 and truth.sources == ("given", "given")
    images = warping_error(list(seq.images), flows=flows, occlusions=occl)
    assert images.mean > 1e-4  # the light moves: the images themselves change
    estimated = warping_error(list(seq.reflectance), list(seq.images))
    assert estimated.sources == ("estimated", "estimated") and len(estimated.pairs) == 2
    assert all(0 < v <= 1 for v in estimated.valid)


def test_pair_warping_error_definition():
    a = torch.full((1, 3, 8, 8), 0.5)
    b = torch.full((1, 3, 8, 8), 0.25)
    valid = torch.ones(1, 1, 8, 8, dtype=torch.bool)
    valid[..., :4] = False
    zero = torch.zeros(1, 2, 8, 8)
    lin = pair_warping_error(a, b, zero, valid, space="linear")
    assert lin == pytest.approx(3 * 0.25**2)  # channel sum, mean over valid pixels
    srgb = pair_warping_error(a, b, zero, valid)  # the default: sRGB values
    assert srgb == pytest.approx(
        3 * (linear_to_srgb(torch.tensor(0.5)) - linear_to_srgb(torch.tensor(0.25))).item() ** 2,
        rel=1e-5,
    )
    assert math.isnan(pair_warping_error(a, b, zero, torch.zeros_like(valid)))
