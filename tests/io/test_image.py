import cv2
import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ImageError
from torchiid.io import linear_to_srgb, load_image, load_mask, save_image, srgb_to_linear


def _write(path, arr):
    assert cv2.imwrite(str(path), arr)
    return path


def test_srgb_roundtrip_matches_reference_curve():
    x = torch.linspace(0, 1, 101, dtype=torch.float64).view(1, 1, 1, -1).expand(1, 3, 1, -1)
    lin = srgb_to_linear(x)
    ref = torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    assert torch.allclose(lin, ref, atol=1e-6)
    assert torch.allclose(linear_to_srgb(lin), x, atol=1e-6)


def test_8bit_is_decoded_from_srgb(tmp_path):
    arr = np.full((64, 70, 3), 128, np.uint8)
    arr[..., 0] = 255  # BGR on disk: blue channel full
    img = load_image(_write(tmp_path / "a.png", arr))
    assert img.bit_depth == 8 and img.image.shape == (3, 64, 70) and img.mask is None
    assert img.image.dtype == torch.float32
    assert abs(float(img.image[0, 0, 0]) - ((128 / 255 + 0.055) / 1.055) ** 2.4) < 1e-5
    assert float(img.image[2, 0, 0]) == pytest.approx(1.0)  # RGB order restored


def test_16bit_keeps_precision_and_linear_flag(tmp_path):
    arr = np.arange(64 * 64 * 3, dtype=np.uint16).reshape(64, 64, 3) * 5
    img = load_image(_write(tmp_path / "a.png", arr), linear=True)
    assert img.bit_depth == 16 and img.linear_file
    expect = torch.from_numpy(arr[..., ::-1].astype(np.float32) / 65535).permute(2, 0, 1)
    assert torch.allclose(img.image, expect, atol=1e-7)
    # 16 bits survive: neighbouring values differ by 5/65535, far below 8-bit steps
    assert float((img.image[:, 0, 1] - img.image[:, 0, 0]).abs().max()) < 1 / 255


def test_gray_is_promoted_and_alpha_becomes_mask(tmp_path):
    gray = np.full((60, 61), 200, np.uint8)
    img = load_image(_write(tmp_path / "g.png", gray))
    assert img.image.shape == (3, 60, 61)
    assert torch.allclose(img.image[0], img.image[2], atol=1e-6)
    rgba = np.zeros((64, 64, 4), np.uint8)
    rgba[..., 3] = 0
    rgba[10:30, 10:30, 3] = 255
    path = _write(tmp_path / "rgba.png", rgba)
    img = load_image(path)
    assert img.mask.shape == (1, 64, 64) and int(img.mask.sum()) == 400
    with pytest.raises(ImageError, match="alpha channel"):
        load_image(path, alpha="error")
    assert load_image(path, alpha="ignore").mask is None


def test_float_npy_is_linear(tmp_path):
    arr = np.random.default_rng(0).random((64, 64, 3)).astype(np.float32) * 2
    np.save(tmp_path / "f.npy", arr)
    img = load_image(tmp_path / "f.npy")
    assert img.bit_depth == 32 and img.linear_file
    assert torch.allclose(img.image.permute(1, 2, 0), torch.from_numpy(arr))


@pytest.mark.parametrize(
    ("name", "make", "message"),
    [
        ("missing.png", None, "no such file"),
        ("empty.png", lambda p: p.write_bytes(b""), "is empty"),
        ("text.png", lambda p: p.write_text("hello, not a picture"), "not an image"),
        ("small.png", lambda p: _write(p, np.zeros((20, 80, 3), np.uint8)), "at least 60 px"),
        ("nan.npy", lambda p: np.save(p, np.full((64, 64, 3), np.nan, np.float32)), "NaN"),
        ("zero.npy", lambda p: np.save(p, np.zeros((0, 64, 3), np.float32)), "zero size"),
        ("five.npy", lambda p: np.save(p, np.zeros((64, 64, 5), np.float32)), "5 channels"),
        ("neg.npy", lambda p: np.save(p, -np.ones((64, 64, 3), np.float32)), "negative"),
    ],
)
def test_bad_files_get_one_line_errors(tmp_path, name, make, message):
    path = tmp_path / name
    if make is not None:
        make(path)
    with pytest.raises(ImageError, match=message) as info:
        load_image(path)
    text = str(info.value)
    assert name in text and "\n" not in text


def test_directory_is_rejected(tmp_path):
    with pytest.raises(ImageError, match="is a directory"):
        load_image(tmp_path)


@pytest.mark.parametrize("encoding", ["srgb8", "srgb16", "linear16", "npy"])
def test_save_then_load_roundtrip(tmp_path, encoding):
    x = torch.rand(3, 64, 66, generator=torch.Generator().manual_seed(0))
    path = tmp_path / ("out.npy" if encoding == "npy" else "out.png")
    save_image(path, x, encoding)
    back = load_image(path, linear=(encoding == "linear16")).image
    tol = {"srgb8": 5e-3, "srgb16": 1e-4, "linear16": 1e-5, "npy": 0}[encoding]
    assert float((back - x).abs().max()) <= tol
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temp file left behind


def test_save_is_atomic_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "keep.png"
    save_image(target, torch.zeros(3, 64, 64))
    before = target.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("torchiid.io.image.os.replace", boom)
    with pytest.raises(OSError, match="disk full"):
        save_image(target, torch.ones(3, 64, 64))
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


def test_load_mask(tmp_path):
    m = np.zeros((64, 64), np.uint8)
    m[5:9, 5:9] = 255
    mask = load_mask(_write(tmp_path / "m.png", m), shape=(64, 64))
    assert mask.dtype == torch.bool and int(mask.sum()) == 16
    with pytest.raises(ImageError, match="mask is 64x64 px but the image is 70x64 px"):
        load_mask(tmp_path / "m.png", shape=(64, 70))
    _write(tmp_path / "empty.png", np.zeros((64, 64), np.uint8))
    with pytest.raises(ImageError, match="mask is empty"):
        load_mask(tmp_path / "empty.png")


def test_encoded_codes_are_the_files_save_codes_writes(tmp_path):
    from torchiid.io.image import encode_codes, save_codes, save_encoded

    rng = np.random.default_rng(3)
    arrays = {
        "rgb8": rng.integers(0, 256, (37, 53, 3), dtype=np.uint8),
        "rgb16": rng.integers(0, 65536, (37, 53, 3), dtype=np.uint16),
        "gray8": rng.integers(0, 256, (37, 53), dtype=np.uint8),
    }
    for name, arr in arrays.items():
        a, b = tmp_path / f"{name}-a.png", tmp_path / f"{name}-b.png"
        save_codes(a, arr)
        save_encoded(b, encode_codes(arr))
        assert a.read_bytes() == b.read_bytes()
        back = cv2.imread(str(b), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(back[..., ::-1] if arr.ndim == 3 else back, arr)
    with pytest.raises(ImageError, match="uint8 or uint16"):
        encode_codes(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ImageError, match="3 colour channels"):
        encode_codes(np.zeros((4, 4, 4), np.uint8))
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left
