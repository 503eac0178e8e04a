"""OpenEXR writing (save_image(..., "exr")) and reading (read_exr, load_image)."""

import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ImageError
from torchiid.io import load_image, read_exr, save_image

OpenEXR = pytest.importorskip("OpenEXR")


def _hdr_values(shape, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.random(shape).astype(np.float32) * 50  # values well above 1
    flat = x.reshape(-1)
    flat[:4] = [0.0, 1e-30, 3e-39, 65504.5]  # zero, tiny, subnormal, above the half range
    return x


def _independent(path):
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        header = dict(exr.header())  # copies: the File clears them when it is closed
        return header, {name: ch.pixels.copy() for name, ch in exr.channels().items()}


def test_rgb_roundtrip_is_exact_and_unclipped(tmp_path):
    x = torch.from_numpy(_hdr_values((3, 40, 50)))
    path = save_image(tmp_path / "out.exr", x, "exr")
    arr, meta = read_exr(path)
    assert arr.dtype == np.float32 and arr.shape == (40, 50, 3)
    np.testing.assert_array_equal(arr, x.permute(1, 2, 0).numpy())
    assert meta == {}
    header, channels = _independent(path)
    assert sorted(channels) == ["B", "G", "R"]
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    assert all(c.dtype == np.float32 for c in channels.values())
    np.testing.assert_array_equal(channels["G"], x[1].numpy())
    assert [p.name for p in tmp_path.iterdir()] == ["out.exr"]  # no temp file left behind


@pytest.mark.parametrize("shape", [(1, 30, 40), (30, 40)])
def test_gray_is_one_y_channel(tmp_path, shape):
    x = _hdr_values(shape)
    image = torch.from_numpy(x) if len(shape) == 3 else x
    path = save_image(tmp_path / "g.exr", image, "exr")
    _, channels = _independent(path)
    assert list(channels) == ["Y"]
    arr, _ = read_exr(path)
    assert arr.shape == (30, 40)
    np.testing.assert_array_equal(arr, x.reshape(30, 40))


def test_metadata_survives(tmp_path):
    meta = {"exposure": 0.1, "scale": 1e-300, "count": 3, "note": "linear, wörld"}
    path = save_image(tmp_path / "m.exr", torch.ones(3, 8, 8), "exr", metadata=meta)
    _, back = read_exr(path)
    assert back == {"exposure": 0.1, "scale": 1e-300, "count": 3.0, "note": "linear, wörld"}
    assert isinstance(back["exposure"], float)
    header, _ = _independent(path)
    assert header["note"] == "linear, wörld"
    assert float(np.asarray(header["exposure"]).reshape(())) == 0.1  # a double, not a float


@pytest.mark.parametrize(
    ("metadata", "message"),
    [
        ({"compression": "none"}, "reserved"),
        ({"channels": 1.0}, "reserved"),
        ({"flag": True}, "float or a str"),
        ({"v": [1.0, 2.0]}, "float or a str"),
        ({"": 1.0}, "non-empty"),
    ],
)
def test_bad_metadata_is_rejected_before_writing(tmp_path, metadata, message):
    with pytest.raises(ValueError, match=message):
        save_image(tmp_path / "bad.exr", torch.ones(3, 8, 8), "exr", metadata=metadata)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("encoding", ["srgb8", "npy"])
def test_metadata_only_for_exr(tmp_path, encoding):
    with pytest.raises(ValueError, match="encoding='exr'"):
        save_image(tmp_path / "x.png", torch.ones(3, 8, 8), encoding, metadata={"a": 1.0})
    save_image(tmp_path / "x.npy", torch.ones(3, 8, 8), "npy", metadata={})  # empty is fine


def test_bad_shape_for_exr(tmp_path):
    with pytest.raises(ImageError, match="gray or RGB"):
        save_image(tmp_path / "x.exr", np.ones((8, 8, 4), np.float32), "exr")


def test_exr_write_is_atomic(tmp_path, monkeypatch):
    target = save_image(tmp_path / "keep.exr", torch.ones(3, 8, 8), "exr")
    before = target.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("torchiid.io.write.os.replace", boom)
    with pytest.raises(OSError, match="disk full"):
        save_image(target, torch.zeros(3, 8, 8), "exr")
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.exr"]


def test_load_image_reads_exr_as_linear_float(tmp_path):
    x = torch.from_numpy(_hdr_values((3, 64, 70)))
    path = save_image(tmp_path / "c.exr", x, "exr")
    loaded = load_image(path, linear=False)  # linear=False does not matter for float files
    assert loaded.bit_depth == 32 and loaded.linear_file and loaded.orientation == 1
    assert torch.equal(loaded.image, x)
    gray = save_image(tmp_path / "g.exr", x[:1], "exr")
    promoted = load_image(gray).image
    assert promoted.shape == (3, 64, 70)
    assert torch.equal(promoted[0], x[0]) and torch.equal(promoted[2], x[0])


def test_half_float_and_alpha_from_other_writers(tmp_path):
    h = (np.random.default_rng(1).random((64, 64)) * 4).astype(np.float16)
    a = np.zeros((64, 64), np.float16)
    a[:10, :20] = 1
    path = tmp_path / "half.exr"
    header = {"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"R": h, "G": h, "B": h, "A": a}) as exr:
        exr.write(str(path))
    arr, _ = read_exr(path)
    assert arr.dtype == np.float32 and arr.shape == (64, 64, 4)
    np.testing.assert_array_equal(arr[..., 1], h.astype(np.float32))
    loaded = load_image(path)
    assert int(loaded.mask.sum()) == 200
    assert torch.equal(loaded.image[0], torch.from_numpy(h.astype(np.float32)))


def test_unusable_exr_files(tmp_path, capsys):
    z = tmp_path / "depth.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"Z": np.ones((8, 8), "f")}) as f:
        f.write(str(z))
    with pytest.raises(ImageError, match=r"channels \['Z'\]; expected Y or R, G, B"):
        read_exr(z)
    good = save_image(tmp_path / "good.exr", torch.from_numpy(_hdr_values((3, 64, 64))), "exr")
    data = good.read_bytes()
    cut = tmp_path / "cut.exr"
    cut.write_bytes(data[: len(data) * 6 // 10])
    for loader in (read_exr, load_image):
        with pytest.raises(ImageError, match="cut.exr: is") as info:
            loader(cut)
        assert "\n" not in str(info.value)
    capsys.readouterr()  # the OpenEXR package prints its own warning
    png = tmp_path / "not.exr"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    with pytest.raises(ImageError, match="not.exr: is not an OpenEXR file"):
        read_exr(png)
    with pytest.raises(ImageError, match="no such file"):
        read_exr(tmp_path / "missing.exr")
