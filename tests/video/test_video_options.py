"""torchiid.video.options: how the frames of a video are tied together."""

import pytest

from torchiid.core.exceptions import ParameterError
from torchiid.video import VideoOptions


def test_options_are_checked():
    with pytest.raises(ParameterError):
        VideoOptions(temporal_norm="l0")
    with pytest.raises(ParameterError):
        VideoOptions(temporal_weight=-1)
    with pytest.raises(ParameterError):
        VideoOptions(flow="magic")
    with pytest.raises(ParameterError):
        VideoOptions(init_median=2)
    assert VideoOptions().weight == 4.0 and VideoOptions(temporal_norm="l1").weight == 1.0


@pytest.mark.parametrize(
    "bad",
    [{"target_sigma": -1.0}, {"later_iterations": -1}, {"reuse_max_frames": -1}],
)
def test_negative_counts_and_widths_are_refused(bad):
    with pytest.raises(ParameterError):
        VideoOptions(**bad)


def test_frame_by_frame_ties_nothing_and_replace_keeps_the_rest():
    alone = VideoOptions.frame_by_frame()
    assert not alone.linked and alone.weight == 0.0
    assert VideoOptions().linked
    assert VideoOptions(temporal_weight=0.0, warm_start=False, match_scale=False).linked
    changed = VideoOptions().replace(flow="farneback")
    assert changed.flow == "farneback" and changed.init_median == VideoOptions().init_median
