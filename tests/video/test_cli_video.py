"""``torchiid decompose-video`` and ``torchiid eval video``: files, statuses, errors."""

import json
import sys

import cv2
import numpy as np
import pytest

import torchiid
from torchiid.cli import main
from torchiid.eval.video import write_flo
from torchiid.io import save_image
from torchiid.synthetic import moving_mondrian

FAST = ["--iterations", "1", "--no-progress"]
FILES = [
    "reflectance.png",
    "shading.png",
    "preview.png",
    "reflectance-linear16.png",
    "shading.exr",
    "info.json",
]


@pytest.fixture(scope="module")
def seq():
    return moving_mondrian(72, 96, frames=4, velocity=(3, 1), light_step=0.1)


@pytest.fixture(scope="module")
def frames(tmp_path_factory, seq):
    d = tmp_path_factory.mktemp("frames")
    for t, img in enumerate(seq.images):
        save_image(d / f"frame_{t + 1:04d}.png", img, "srgb8")
    return d


def snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_writes_every_frame_and_the_parameters(frames, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["decompose-video", str(frames), "-o", str(out), "--save-npy", *FAST]) == 0
    for i in range(1, 5):
        for name in [*FILES, "reflectance.npy", "shading.npy"]:
            assert (out / f"frame-{i:06d}-{name}").is_file(), name
    info = json.loads((out / "frame-000002-info.json").read_text())
    assert info["frame_name"] == "frame_0002.png" and info["linked_to_previous"] is True
    assert 0 < info["trusted_share"] <= 1 and info["scale"] > 0
    first = json.loads((out / "frame-000001-info.json").read_text())
    assert first["linked_to_previous"] is False
    assert info["shading_white"] == first["shading_white"]  # one view scale for the sequence
    params = json.loads((out / "video-params.json").read_text())
    assert params["params"]["iterations"] == 1 and params["video"]["temporal_norm"] == "l2"
    assert params["torchiid_version"] == info["torchiid_version"] == torchiid.__version__
    assert not (out / "frame-000001-params.json").exists()
    r = np.load(out / "frame-000003-reflectance.npy")
    s = np.load(out / "frame-000003-shading.npy")
    from torchiid.io import load_image

    img = load_image(frames / "frame_0003.png").image.permute(1, 2, 0).numpy()
    assert np.allclose(r * s[..., None], img, atol=1e-5) and r.max() <= 1
    assert not list(out.glob(".*"))  # no temporary files left behind


def test_existing_outputs_are_kept_and_the_chain_resumes(frames, tmp_path, capsys):
    first_two = tmp_path / "two"
    first_two.mkdir()
    for f in sorted(frames.iterdir())[:2]:
        (first_two / f.name).write_bytes(f.read_bytes())
    out = tmp_path / "out"
    assert main(["decompose-video", str(first_two), "-o", str(out), *FAST]) == 0
    before = snapshot(out)
    capsys.readouterr()
    # other settings would be mixed into the chain: stopped before any frame, in one line
    for changed, key in [
        (["--iterations", "2", "--no-progress"], "params.iterations 1 -> 2"),
        ([*FAST, "--temporal-weight", "2"], "video.temporal_weight 4.0 -> 2.0"),
        ([*FAST, "--flow", "farneback"], "video.flow 'dis' -> 'farneback'"),
    ]:
        assert main(["decompose-video", str(frames), "-o", str(out), *changed]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "video-params.json" in err[0] and key in err[0], err
        assert "--overwrite" in err[0] and snapshot(out) == before
    # files of another torchiid version: the version is no setting, the chain resumes
    params = json.loads((out / "video-params.json").read_text())
    (out / "video-params.json").write_text(json.dumps({**params, "torchiid_version": "0.9.0"}))
    before["video-params.json"] = (out / "video-params.json").read_bytes()
    # the whole sequence into the same folder: frames 1-2 exist (skipped as done), 3-4 are new
    assert main(["decompose-video", str(frames), "-o", str(out), *FAST]) == 0
    err = capsys.readouterr().err
    assert "2 frame(s) written, 2 skipped" in err and "error" not in err
    after = snapshot(out)
    assert all(after[name] == data for name, data in before.items())  # byte for byte
    info = json.loads((out / "frame-000003-info.json").read_text())
    assert info["linked_to_previous"] is True  # continued from frame 2's files
    # a frame with only some of its files is no finished frame: reported, status 1
    (out / "frame-000004-preview.png").unlink()
    assert main(["decompose-video", str(frames), "-o", str(out), *FAST]) == 1
    err = capsys.readouterr().err
    assert "frame-000004-*: written earlier without frame-000004-preview.png" in err
    assert "1 of 4 frame(s) failed" in err and "0 frame(s) written, 3 skipped" in err
    assert main(["decompose-video", str(frames), "-o", str(out), "--overwrite", *FAST]) == 0


def test_a_bad_frame_is_reported_and_the_others_written(frames, tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    for f in frames.iterdir():
        (src / f.name).write_bytes(f.read_bytes())
    data = (src / "frame_0002.png").read_bytes()
    (src / "frame_0002.png").write_bytes(data[: len(data) // 2])  # truncated
    out = tmp_path / "out"
    assert main(["decompose-video", str(src), "-o", str(out), *FAST]) == 1
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "error" in ln]
    assert len(lines) == 1 and "frame_0002.png" in lines[0]
    assert not list(out.glob("frame-000002-*"))
    assert (out / "frame-000004-reflectance.png").exists()


def test_masks_per_frame(frames, tmp_path, capsys):
    masks = tmp_path / "masks"
    masks.mkdir()
    m = np.zeros((72, 96), np.uint8)
    m[10:60, 12:80] = 255
    for t in range(4):
        cv2.imwrite(str(masks / f"m{t}.png"), m)
    out = tmp_path / "out"
    args = ["decompose-video", str(frames), "-o", str(out), "--masks", str(masks), *FAST]
    assert main(args) == 0
    r = cv2.imread(str(out / "frame-000003-reflectance.png"))
    assert r[:10].max() == 0 and r[12:58, 14:78].max() > 0
    (masks / "m3.png").unlink()
    assert main([*args, "--overwrite"]) == 2
    assert "3 masks but" in capsys.readouterr().err


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: d / "missing", "no such file or folder"),
        (lambda d: d / "frames" / "frame_0001.png", "is a single image"),
        (lambda d: (d / "empty").mkdir() or d / "empty", "holds no image files"),
    ],
)
def test_usage_errors_exit_2(frames, tmp_path, capsys, make, message):
    (tmp_path / "frames").symlink_to(frames)
    src = make(tmp_path)
    assert main(["decompose-video", str(src), "-o", str(tmp_path / "out"), *FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("torchiid: error:") and message in err[0]
    assert not (tmp_path / "out").exists()


def test_options_are_checked(frames, tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main(["decompose-video", str(frames), "-o", out, "--temporal-weight", "-1"]) == 2
    assert "--temporal-weight" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    assert main(["decompose-video", str(frames), "-o", str(tmp_path / "file"), *FAST]) == 2


def test_interrupted_frame_leaves_nothing(frames, tmp_path, monkeypatch, capsys):
    out = tmp_path / "out"
    monkeypatch.setenv("TORCHIID_TEST_INTERRUPT", "write:2")  # inside the first frame's set
    assert main(["decompose-video", str(frames), "-o", str(out), *FAST]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert not out.exists() or not list(out.iterdir())
    monkeypatch.delenv("TORCHIID_TEST_INTERRUPT")
    assert main(["decompose-video", str(frames), "-o", str(out), *FAST]) == 0


def test_eval_video_with_estimated_and_given_flow(frames, seq, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["decompose-video", str(frames), "-o", str(out), *FAST]) == 0
    flow = tmp_path / "flow"
    flow.mkdir()
    for t in range(3):  # Sintel layout: frame_0001.flo is the flow from frame 1 to 2
        write_flo(flow / f"frame_{t + 1:04d}.flo", seq.flow[t])
        occ = (~seq.valid[t, 0]).numpy().astype(np.uint8) * 255
        cv2.imwrite(str(flow / f"occlusions_{t + 1:04d}.png"), occ)
    capsys.readouterr()
    summary = tmp_path / "eval"
    args = ["eval", "video", str(frames), str(out), "--flow", str(flow), "-o", str(summary)]
    assert main([*args, "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "frame_0001.png -> frame_0002.png" in text and "mean" in text
    data = json.loads((summary / "video-summary.json").read_text())
    assert len(data["pairs"]) == 3 and data["mean"]["given"] is not None
    assert data["torchiid_version"] == torchiid.__version__
    assert all(p["given_valid"] < 1 for p in data["pairs"])  # the occlusion maps were read
    assert data["pairs"][1]["occlusion_file"] == str(flow / "occlusions_0002.png")
    # the reflectance flickers less than the input frames themselves (same flow, same pixels)
    assert data["mean"]["estimated"] < data["mean"]["input_estimated"]
    assert data["mean"]["given"] < data["mean"]["input_given"]
    assert main([*args, "--no-progress"]) == 2  # the summary exists
    assert main(["eval", "video", str(frames), "--no-progress"]) == 2
    assert main(["eval", "mit", str(frames), str(out)]) == 2


def test_eval_video_occlusions_folder_in_sintel_layout(frames, seq, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["decompose-video", str(frames), "-o", str(out), *FAST]) == 0
    # MPI Sintel: flow/<scene>/frame_0001.flo, occlusions/<scene>/frame_0001.png (1 -> 2)
    flow, occl = tmp_path / "flow" / "scene", tmp_path / "occlusions" / "scene"
    flow.mkdir(parents=True)
    occl.mkdir(parents=True)
    for t in range(3):
        write_flo(flow / f"frame_{t + 1:04d}.flo", seq.flow[t])
    occ = (~seq.valid[1, 0]).numpy().astype(np.uint8) * 255
    cv2.imwrite(str(occl / "frame_0002.png"), occ)  # matched by number: pair 2 -> 3 only
    summary = tmp_path / "eval"
    args = ["eval", "video", str(frames), str(out), "--flow", str(flow), "--no-progress"]
    assert main([*args, "--occlusions", str(occl), "-o", str(summary)]) == 0
    data = json.loads((summary / "video-summary.json").read_text())
    files = [p["occlusion_file"] for p in data["pairs"]]
    assert files == [None, str(occl / "frame_0002.png"), None]
    assert data["pairs"][1]["given_valid"] == pytest.approx(float(seq.valid[1].float().mean()))
    capsys.readouterr()
    assert main(["eval", "video", str(frames), str(out), "--occlusions", str(occl)]) == 2
    assert "give --flow" in capsys.readouterr().err
    (occl / "frame_2.png").write_bytes((occl / "frame_0002.png").read_bytes())
    assert main([*args, "--occlusions", str(occl)]) == 2
    assert "two occlusion maps for frame 2" in capsys.readouterr().err
    # the estimated columns can use another estimator than the method's DIS
    assert main([*args, "--eval-flow", "farneback", "-o", str(tmp_path / "fb")]) == 0
    assert json.loads((tmp_path / "fb" / "video-summary.json").read_text())["eval_flow"] == (
        "farneback"
    )


def test_eval_video_reports_missing_results(frames, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["decompose-video", str(frames), "-o", str(out), *FAST]) == 0
    for p in out.glob("frame-000004-*"):
        p.unlink()
    assert main(["eval", "video", str(frames), str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "frame 4" in err and "frame_0004.png" in err


# ----------------------------------------------------------------------------- video files


def write_mp4(path, seq):
    av = pytest.importorskip("av")
    from torchiid.io.layers import srgb8_from_linear

    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height = 96, 72
        stream.pix_fmt = "yuv444p"
        stream.options = {"crf": "0"}
        for img in seq.images:
            frame = av.VideoFrame.from_ndarray(srgb8_from_linear(img), format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def test_video_file_in_and_preview_out(seq, tmp_path):
    av = pytest.importorskip("av")
    clip = tmp_path / "clip.mp4"
    write_mp4(clip, seq)
    out = tmp_path / "out"
    assert main(["decompose-video", str(clip), "-o", str(out), "--preview", *FAST]) == 0
    assert len(list(out.glob("frame-*-reflectance.png"))) == 4
    info = json.loads((out / "frame-000004-info.json").read_text())
    assert info["frame_name"] == "clip.mp4 frame 4"
    with av.open(str(out / "preview.mp4")) as c:
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
        rate = c.streams.video[0].average_rate
    assert len(decoded) == 4 and decoded[0].shape == (72, 3 * 96 + 8, 3)
    assert float(rate) == pytest.approx(10)  # the video's own frame rate
    # the middle panel is the reflectance PNG
    r = cv2.imread(str(out / "frame-000002-reflectance.png"))[..., ::-1].astype(float)
    assert np.abs(decoded[1][:, 100:196].astype(float) - r).mean() < 12
    # run again: every frame and the preview are done
    preview = (out / "preview.mp4").read_bytes()
    assert main(["decompose-video", str(clip), "-o", str(out), "--preview", *FAST]) == 0
    # a frame written now is missing from the kept preview: reported, the preview kept
    for f in out.glob("frame-000004-*"):
        f.unlink()
    assert main(["decompose-video", str(clip), "-o", str(out), "--preview", *FAST]) == 1
    assert (out / "preview.mp4").read_bytes() == preview
    assert (out / "frame-000004-reflectance.png").exists()


def test_video_file_without_pyav(seq, tmp_path, monkeypatch, capsys):
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"\x00\x00\x00\x18ftypmp42")
    monkeypatch.setitem(sys.modules, "av", None)  # import av raises ImportError
    assert main(["decompose-video", str(clip), "-o", str(tmp_path / "out"), *FAST]) == 2
    assert "pip install 'torchiid[video]'" in capsys.readouterr().err


def test_a_broken_video_file_is_one_line(tmp_path, capsys):
    pytest.importorskip("av")
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"not a video at all" * 100)
    assert main(["decompose-video", str(clip), "-o", str(tmp_path / "out"), *FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "clip.mp4: cannot open as a video" in err[0]


def test_a_video_of_frames_below_the_patch_size_is_refused_before_any_frame(tmp_path, capsys):
    av = pytest.importorskip("av")
    clip = tmp_path / "tiny.mp4"
    with av.open(str(clip), mode="w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        for i in range(3):
            rgb = np.full((48, 64, 3), 40 * (i + 1), np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    out = tmp_path / "out"
    assert main(["decompose-video", str(clip), "-o", str(out), *FAST]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tiny.mp4: its frames are 64x48 px; at least 60 px" in err[0], err
    assert not out.exists()


def test_a_folder_of_another_version_with_the_same_settings_resumes(tmp_path):
    from torchiid.commands.video import _check_same_settings, _params_json
    from torchiid.core.exceptions import TorchiidError
    from torchiid.params import Parameters
    from torchiid.video import VideoOptions
    from torchiid.video.write import PARAMS_NAME

    params, options = Parameters().replace(iterations=1), VideoOptions()
    written = json.loads(_params_json(params, options))
    assert written["torchiid_version"] == written["params"]["torchiid_version"]
    written["torchiid_version"] = written["params"]["torchiid_version"] = "0.9.0"
    (tmp_path / PARAMS_NAME).write_text(json.dumps(written))
    _check_same_settings(tmp_path, params, options)  # the version is no setting
    with pytest.raises(TorchiidError, match="iterations 1 -> 2"):
        _check_same_settings(tmp_path, params.replace(iterations=2), options)
