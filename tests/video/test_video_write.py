"""torchiid.video.write: a frame's files under its stem, and the MP4 preview."""

import pytest
import torch

from torchiid.io.output_set import OutputError
from torchiid.video.write import PreviewWriter, frame_file_names, frame_stem


def test_frames_are_numbered_from_one_without_their_own_parameters():
    assert frame_stem(0) == "frame-000001" and frame_stem(41) == "frame-000042"
    names = frame_file_names("frame-000001", save_npy=True)
    assert "frame-000001-reflectance.npy" in names and not any("params" in n for n in names)


def test_preview_writer_puts_the_video_in_place_at_the_end(tmp_path):
    av = pytest.importorskip("av")
    target = tmp_path / "preview.mp4"
    writer = PreviewWriter(target, fps=10)
    g = torch.Generator().manual_seed(0)
    for _ in range(3):
        image = torch.rand(3, 45, 61, generator=g)
        writer.add(image, image, torch.rand(1, 45, 61, generator=g))
        assert not target.exists()  # a hidden temporary file until the commit
    assert writer.commit() == target
    assert [p.name for p in tmp_path.iterdir()] == ["preview.mp4"]
    with av.open(str(target)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    # three 45x61 panels with 4 px between, padded to even sides for yuv420p
    assert len(frames) == 3 and frames[0].shape == (46, 3 * 61 + 8 + 1, 3)
    again = PreviewWriter(target)
    again.add(image, image, torch.rand(1, 45, 61, generator=g))
    with pytest.raises(OutputError, match="exists; pass --overwrite"):
        again.commit()
    assert [p.name for p in tmp_path.iterdir()] == ["preview.mp4"]  # nothing left behind
