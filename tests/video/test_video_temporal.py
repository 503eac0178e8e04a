"""The video loop on the synthetic moving Mondrian: consistency, accuracy, conventions."""

import pytest
import torch

from torchiid.eval.lmse import mit_lmse
from torchiid.eval.video import warping_error
from torchiid.params import Parameters
from torchiid.synthetic import moving_mondrian
from torchiid.video import VideoDecomposer, VideoOptions, warp

# The paper's shading weights (no S_s): frame by frame, their shading steps at the Mondrian's
# chromaticity edges by an amount that changes from frame to frame, the flicker the video loop
# is for. With S_s (the default) this sequence hardly flickers frame by frame (the warping
# errors are on the documentation's Benchmarks page), so it cannot show what the loop removes.
PARAMS = Parameters().replace(iterations=3, lambda_m=0.02, lambda_s=0.0)
FAST = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)


@pytest.fixture(scope="module")
def sequence():
    # 96x72, 5 frames: the surface moves 3 px left and 1 px up per frame, the light turns
    return moving_mondrian(72, 96, frames=5, velocity=(3, 1), light_step=0.1, seed=0)


def run(seq, options, params=PARAMS):
    video = VideoDecomposer(params, options)
    return [video(img) for img in seq.images]


def scores(seq, frames):
    n = len(frames)
    refl = [f.reflectance for f in frames]
    flows = [seq.flow[t : t + 1] for t in range(n - 1)]
    occl = [~seq.valid[t : t + 1] for t in range(n - 1)]
    true_flow = warping_error(refl, flows=flows, occlusions=occl).mean
    estimated = warping_error(refl, list(seq.images)).mean
    lmse = (
        sum(
            float(
                mit_lmse(
                    seq.reflectance[t : t + 1], seq.shading[t : t + 1], f.reflectance, f.shading
                )
            )
            for t, f in enumerate(frames)
        )
        / n
    )
    return true_flow, estimated, lmse


@pytest.fixture(scope="module")
def frame_by_frame(sequence):
    return scores(sequence, run(sequence, VideoOptions.frame_by_frame()))


@pytest.mark.parametrize(
    "options",
    [VideoOptions(), VideoOptions(temporal_norm="l1")],
    ids=["l2-default", "l1"],
)
def test_temporal_consistency_on_the_moving_mondrian(sequence, frame_by_frame, options):
    frames = run(sequence, options)
    we_true, we_est, lmse = scores(sequence, frames)
    fb_true, fb_est, fb_lmse = frame_by_frame
    # the video loop's targets: at least 3x less warping error, per-frame LMSE at most 5% worse
    assert we_true * 3 <= fb_true, (we_true, fb_true)
    assert lmse <= 1.05 * fb_lmse, (lmse, fb_lmse)
    # also measured with the flow estimated on the frames, as for a real video
    assert we_est * 2 <= fb_est, (we_est, fb_est)
    assert all(f.linked for f in frames[1:]) and not frames[0].linked
    assert all(f.trusted > 0.5 for f in frames[1:])


def test_with_the_default_shading_weights_the_loop_is_still_more_consistent(sequence):
    # with S_s this sequence hardly flickers frame by frame; the loop must not make it worse
    default = Parameters().replace(iterations=3)
    fb_true, fb_est, _ = scores(sequence, run(sequence, VideoOptions.frame_by_frame(), default))
    we_true, we_est, _ = scores(sequence, run(sequence, VideoOptions(), default))
    assert we_true <= fb_true, (we_true, fb_true)
    assert we_est * 1.2 <= fb_est, (we_est, fb_est)


def test_one_albedo_convention_for_the_sequence(sequence):
    frames = run(sequence, VideoOptions(), FAST)
    whites = {float(f.decomposition.shading_white[0]) for f in frames}
    assert len(whites) == 1  # the first frame's shading_white holds throughout
    for f in frames:
        assert float(f.reflectance.min()) >= 0 and float(f.reflectance.max()) <= 1
    assert frames[0].scale == 1.0 and all(f.scale != 1.0 for f in frames[1:])


@pytest.mark.parametrize("match_scale", [True, False])
def test_a_linked_frame_takes_the_previous_frames_albedo_scale(sequence, match_scale):
    # the previous reflectance is remembered at half its scale; with match_scale the next frame
    # follows it (compared along the true flow), without it the frame keeps its own quantile
    first = VideoDecomposer(FAST)(sequence.images[0])
    half = first.reflectance * 0.5
    video = VideoDecomposer(FAST, VideoOptions(match_scale=match_scale))
    video.remember(sequence.images[0], half[0])
    frame = video(sequence.images[1])
    onto_first = warp(frame.reflectance, sequence.flow[0:1])[0]
    ok = sequence.valid[0:1] & (half.sum(1, keepdim=True) > 1e-3)
    ratio = float((onto_first.sum(1, keepdim=True)[ok] / half.sum(1, keepdim=True)[ok]).median())
    if match_scale:
        assert abs(ratio - 1) < 0.02 and frame.scale < 0.75, (ratio, frame.scale)
    else:
        assert abs(ratio - 1) > 0.2 and frame.scale == 1.0, (ratio, frame.scale)


def test_frame_by_frame_is_decompose(sequence):
    from torchiid.model import decompose

    frames = run(sequence, VideoOptions.frame_by_frame(), FAST)
    alone = decompose(sequence.images[2][None], FAST)
    assert torch.equal(frames[2].reflectance, alone.reflectance)
    assert not any(f.linked for f in frames)


def test_feature_reuse_follows_the_motion(sequence):
    frames = run(sequence, VideoOptions(reuse_max_frames=2), FAST)
    reused = [f.features_reused for f in frames]
    assert reused == [False, True, True, False, True]  # recomputed after 2 reuses
    frames = run(sequence, VideoOptions(reuse_max_motion=0.5), FAST)
    assert not any(f.features_reused for f in frames)  # it moves more than 0.5 px


def test_reset_resize_and_remember(sequence):
    video = VideoDecomposer(FAST)
    first = video(sequence.images[0])
    assert video(sequence.images[1]).linked
    video.reset()
    assert not video(sequence.images[2]).linked
    assert not video(sequence.images[3][:, :64, :80]).linked  # another size: a new shot
    video = VideoDecomposer(FAST)
    video.remember(sequence.images[0], first.reflectance[0], shading_white=0.5)
    linked = video(sequence.images[1])
    assert linked.linked and float(linked.decomposition.shading_white[0]) == 0.5


def test_masks_restrict_every_frame(sequence):
    mask = torch.zeros(1, 72, 96, dtype=torch.bool)
    mask[:, 8:64, 10:90] = True
    video = VideoDecomposer(FAST)
    for img in sequence.images[:3]:
        f = video(img, mask)
        assert float(f.reflectance[..., ~mask[0]].abs().max()) == 0
        assert float(f.shading[..., ~mask[0]].abs().max()) == 0
    assert f.linked


def test_a_mask_smaller_than_the_reuse_share_still_reuses_stage0(sequence):
    # the mask covers 65% of the frame, less than reuse_min_trusted = 0.8: the trusted share
    # is one of the masked area, so Stage 0 is reused as without a mask
    mask = torch.zeros(1, 72, 96, dtype=torch.bool)
    mask[:, 8:64, 10:90] = True
    assert float(mask.float().mean()) < VideoOptions().reuse_min_trusted
    video = VideoDecomposer(FAST)
    frames = [video(img, mask) for img in sequence.images[:2]]
    assert frames[1].trusted >= VideoOptions().reuse_min_trusted
    assert frames[1].features_reused
