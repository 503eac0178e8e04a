"""torchiid.video.linking: a frame tied to the previous one on the moving Mondrian."""

import pytest
import torch

from torchiid.synthetic import moving_mondrian
from torchiid.video import VideoOptions
from torchiid.video.linking import Link, Previous, keep_albedo, link_frames, warm_start


@pytest.fixture(scope="module")
def sequence():
    # the content moves by (-3, -1) px per frame under a fixed light
    return moving_mondrian(72, 96, frames=2, velocity=(3, 1), light_step=0.0, seed=1)


def _previous(seq, mask=None):
    return Previous((72, 96), seq.images[0:1], seq.reflectance[0:1], mask, None, 0)


def test_link_follows_the_true_motion(sequence):
    frame = sequence.images[1:2]
    link = link_frames(_previous(sequence), frame, None, frame, VideoOptions())
    assert link.trusted_share > 0.8
    assert abs(link.motion - 10**0.5) < 0.5  # |(3, 1)| px
    inside = link.trusted[0, 0, 4:-4, 4:-4]
    err = (link.target - sequence.reflectance[1:2]).abs().amax(1)[0, 4:-4, 4:-4]
    assert float(err[inside].median()) < 0.01  # the warped reflectance is frame 1's


def test_the_trusted_share_counts_only_the_masked_area(sequence):
    mask = torch.zeros(1, 1, 72, 96, dtype=torch.bool)
    mask[..., 10:60, 20:80] = True
    prev = _previous(sequence, mask)
    link = link_frames(prev, sequence.images[1:2], mask, sequence.images[1:2], VideoOptions())
    assert not bool(link.trusted[~mask].any())
    assert link.trusted_share > 0.8  # of the masked area, not of the whole frame


@pytest.mark.parametrize("init_median", [1, 3])
def test_warm_start_from_an_exact_target_recovers_the_shading(sequence, init_median):
    img, refl, shading = sequence.images[1:2], sequence.reflectance[1:2], sequence.shading[1:2]
    trusted = torch.ones(1, 1, 72, 96, dtype=torch.bool)
    link = Link(torch.zeros(1, 2, 72, 96), trusted, refl, 1.0, 0.0)
    r0, s0 = warm_start(img, link, 1e-4, init_median)
    tol = 1e-5 if init_median == 1 else 0.05  # the median moves the shading's own edges a little
    torch.testing.assert_close(s0, shading, atol=tol, rtol=0)
    if init_median == 1:
        assert torch.equal(r0, refl)  # the target where it is trusted


def test_keep_albedo_moves_the_excess_into_the_shading():
    refl = torch.tensor([0.2, 0.5, 0.8, 0.9]).view(1, 1, 2, 2).expand(1, 3, 2, 2)
    shading = torch.full((1, 1, 2, 2), 2.0)
    r, s, over = keep_albedo(refl, shading, 1.25, None)
    # at this scale 0.8 reaches 1 and 0.9 goes above it (1.125): clipped, its shading grows
    torch.testing.assert_close(r[0, 0].flatten(), torch.tensor([0.25, 0.625, 1.0, 1.0]))
    torch.testing.assert_close(s[0, 0].flatten(), torch.tensor([1.6, 1.6, 1.6 * 1.0, 1.6 * 1.125]))
    assert float(over) == 0.25  # one pixel of four above 1
