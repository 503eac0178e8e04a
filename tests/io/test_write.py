"""Writing: atomic saves in every encoding, with the permissions of a normal file."""

import os
import stat

import cv2
import numpy as np
import pytest
import torch

import torchiid.io.write as write_module
from torchiid.core.exceptions import ImageError
from torchiid.io import load_image, save_image, save_uint8
from torchiid.io.write import encode_codes, save_codes, save_encoded


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

    monkeypatch.setattr("torchiid.io.write.os.replace", boom)
    with pytest.raises(OSError, match="disk full"):
        save_image(target, torch.ones(3, 64, 64))
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


def test_encoded_codes_are_the_files_save_codes_writes(tmp_path):
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


@pytest.fixture
def umask():
    previous = os.umask(0o022)
    os.umask(previous)

    def set_umask(value):
        os.umask(value)

    yield set_umask
    os.umask(previous)


def _mode(path):
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize(("mask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_saved_files_follow_the_umask(tmp_path, umask, mask, mode):
    umask(mask)
    x = torch.rand(3, 8, 8)
    written = [
        save_image(tmp_path / "a.png", x),
        save_image(tmp_path / "a.npy", x, "npy"),
        save_image(tmp_path / "a.exr", x, "exr"),
        save_uint8(tmp_path / "u.png", np.zeros((8, 8, 3), np.uint8)),
    ]
    assert [_mode(p) for p in written] == [mode] * 4


def test_umask_fallback_probe_restores_the_umask(tmp_path, umask, monkeypatch):
    real_open = open

    def no_proc(file, *args, **kwargs):
        if str(file) == "/proc/self/status":
            raise OSError("no /proc here")
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(write_module, "open", no_proc, raising=False)
    monkeypatch.setattr(write_module, "_probed_umask", None)
    umask(0o027)
    path = save_image(tmp_path / "b.npy", torch.ones(3, 4, 4), "npy")
    assert _mode(path) == 0o640
    assert os.umask(0o027) == 0o027  # left as it was
