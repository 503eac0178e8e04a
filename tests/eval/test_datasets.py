import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchiid.core.exceptions import ParameterError
from torchiid.eval import (
    DatasetError,
    DenseFolderDataset,
    IIWDataset,
    MITDataset,
    SAWDataset,
    open_dataset,
)

MIT_REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "mit-berkeley"


def _write16(path, rgb_or_gray):
    arr = np.asarray(rgb_or_gray)
    if arr.ndim == 3:
        arr = arr[..., ::-1]  # RGB -> BGR for cv2
    assert cv2.imwrite(str(path), np.ascontiguousarray(arr.astype(np.uint16)))


def _fake_mit(root, name="obj", h=6, w=7, seed=0):
    rng = np.random.default_rng(seed)
    d = root / name
    d.mkdir(parents=True)
    files = {
        "original": rng.integers(0, 65536, (h, w, 3)),
        "diffuse": rng.integers(0, 65536, (h, w, 3)),
        "reflectance": rng.integers(0, 65536, (h, w, 3)),
        "shading": rng.integers(0, 65536, (h, w)),
        "mask": np.where(rng.random((h, w)) > 0.5, 65025, 0),
    }
    for k, v in files.items():
        _write16(d / f"{k}.png", v)
    return files


def test_mit_reader_16bit_roundtrip(tmp_path):
    files = _fake_mit(tmp_path)
    ds = MITDataset(tmp_path)
    assert ds.ids == ("obj",) and len(ds) == 1
    s = ds[0]
    assert s.image.dtype == torch.float32 and s.image.shape == (3, 6, 7)
    np.testing.assert_allclose(
        s.image.permute(1, 2, 0).numpy(), files["diffuse"] / 65535, atol=1e-7
    )
    np.testing.assert_allclose(
        s.reflectance.permute(1, 2, 0).numpy(), files["reflectance"] / 65535, atol=1e-7
    )
    assert s.shading.shape == (1, 6, 7)
    np.testing.assert_allclose(s.shading[0].numpy(), files["shading"] / 65535, atol=1e-7)
    assert s.mask.dtype == torch.bool
    assert torch.equal(s.mask[0], torch.from_numpy(files["mask"] > 0))
    orig = MITDataset(tmp_path, input="original")[0]
    np.testing.assert_allclose(
        orig.image.permute(1, 2, 0).numpy(), files["original"] / 65535, atol=1e-7
    )


def test_mit_reader_errors(tmp_path):
    with pytest.raises(DatasetError):
        MITDataset(tmp_path / "absent")
    with pytest.raises(DatasetError):
        MITDataset(tmp_path)  # empty
    _fake_mit(tmp_path)
    (tmp_path / "obj" / "mask.png").unlink()
    with pytest.raises(DatasetError, match="mask.png"):
        MITDataset(tmp_path, objects=["obj"])
    with pytest.raises(DatasetError):
        MITDataset(tmp_path, input="specular")


def _judgement():
    return {
        "intrinsic_points": [{"id": 1, "x": 0.5, "y": 0.5, "opaque": True}],
        "intrinsic_comparisons": [],
    }


@pytest.mark.parametrize("sub", ["data", ""])
def test_iiw_reader_layouts_and_split(tmp_path, sub):
    d = tmp_path / sub if sub else tmp_path
    d.mkdir(exist_ok=True)
    for i in ("12", "3", "40"):
        img = np.full((4, 5, 3), 128, np.uint8)
        img[0, 0] = (255, 0, 0)  # BGR: blue
        cv2.imwrite(str(d / f"{i}.png"), img)
        (d / f"{i}.json").write_text(json.dumps(_judgement()))
    cv2.imwrite(str(d / "99.png"), np.zeros((4, 5, 3), np.uint8))  # no json: not listed
    ds = IIWDataset(tmp_path)
    assert ds.ids == ("3", "12", "40")
    s = ds[0]
    lin = ((128 / 255 + 0.055) / 1.055) ** 2.4
    assert s.image[:, 1, 1] == pytest.approx(torch.full((3,), lin), abs=1e-6)
    assert s.image[:, 0, 0].tolist() == pytest.approx([0.0, 0.0, 1.0])  # RGB order
    assert s.judgements["intrinsic_points"][0]["id"] == 1
    assert s.mask.shape == (1, 4, 5) and bool(s.mask.all())
    split = tmp_path / "split.txt"
    split.write_text("40\n\n12\n")
    assert IIWDataset(tmp_path, ids=split).ids == ("40", "12")
    assert [x.id for x in IIWDataset(tmp_path, ids=["3"])] == ["3"]
    with pytest.raises(DatasetError, match="missing"):
        IIWDataset(tmp_path, ids=["3", "77"])


def test_saw_reader(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "labels").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "5.png"), np.zeros((3, 4, 3), np.uint8))
    raw = np.array([[0, 1, 2, 100]] * 3)
    np.save(tmp_path / "labels" / "5.npy", raw)
    s = SAWDataset(tmp_path)[0]
    assert s.labels.tolist() == [[3, 2, 1, 0]] * 3
    assert s.mask[0].tolist() == [[True, True, True, False]] * 3
    same = SAWDataset(tmp_path, release_labels=False)[0]
    assert same.labels.tolist() == raw.tolist()
    np.save(tmp_path / "labels" / "5.npy", np.zeros((2, 2)))
    with pytest.raises(DatasetError, match="do not match"):
        SAWDataset(tmp_path)[0]
    with pytest.raises(DatasetError):
        SAWDataset(tmp_path, image_dir="photos")


def test_dense_folder_reader(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 65536, (5, 6, 3))
    _write16(tmp_path / "a.png", img)
    _write16(tmp_path / "a-reflectance.png", img)
    _write16(tmp_path / "a-shading.png", rng.integers(0, 65536, (5, 6)))
    cv2.imwrite(str(tmp_path / "b.png"), np.full((5, 6, 3), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "b-reflectance.png"), np.full((5, 6, 3), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "b-shading.png"), np.full((5, 6), 64, np.uint8))
    cv2.imwrite(str(tmp_path / "b-mask.png"), np.eye(5, 6, dtype=np.uint8) * 255)
    ds = DenseFolderDataset(tmp_path)
    assert ds.ids == ("a", "b")
    a, b = list(ds)
    np.testing.assert_allclose(a.image.permute(1, 2, 0).numpy(), img / 65535, atol=1e-7)
    assert bool(a.mask.all()) and int(b.mask.sum()) == 5
    lin = ((64 / 255 + 0.055) / 1.055) ** 2.4
    assert b.shading[0, 0, 0].item() == pytest.approx(lin, abs=1e-6)
    assert DenseFolderDataset(tmp_path, srgb=False)[1].shading[0, 0, 0].item() == pytest.approx(
        64 / 255
    )
    (tmp_path / "a-shading.png").unlink()
    with pytest.raises(DatasetError, match="a"):
        DenseFolderDataset(tmp_path)


def test_reader_rejects_alpha_and_size_mismatch(tmp_path):
    _fake_mit(tmp_path)
    cv2.imwrite(str(tmp_path / "obj" / "diffuse.png"), np.zeros((6, 7, 4), np.uint16))
    with pytest.raises(DatasetError, match="alpha"):
        MITDataset(tmp_path)[0]
    _write16(tmp_path / "obj" / "diffuse.png", np.zeros((6, 8, 3)))
    with pytest.raises(DatasetError, match="differ in size"):
        MITDataset(tmp_path)[0]


def test_open_dataset_by_name_with_ids(tmp_path):
    for name in ("im0", "im1", "im2"):
        for suffix in ("", "-reflectance", "-shading"):
            _write16(tmp_path / f"{name}{suffix}.png", np.full((4, 5), 30000))
    assert open_dataset("dense", tmp_path).ids == ("im0", "im1", "im2")
    assert open_dataset("dense", tmp_path, ["im2", "im0"]).ids == ("im2", "im0")
    split = tmp_path / "split.txt"
    split.write_text("im1\n")
    assert open_dataset("dense", tmp_path, split).ids == ("im1",)
    with pytest.raises(DatasetError, match=r"1 of the given ids are not in .*\['im9'\]"):
        open_dataset("dense", tmp_path, ["im9"])
    split.write_text("im8\nim9\n")
    with pytest.raises(DatasetError, match="2 ids of .*split.txt are not in"):
        open_dataset("dense", tmp_path, split)
    with pytest.raises(ParameterError, match="unknown dataset 'kitti'"):
        open_dataset("kitti", tmp_path)
    _fake_mit(tmp_path / "mit")
    assert isinstance(open_dataset("mit", tmp_path / "mit", input="original"), MITDataset)


@pytest.mark.skipif(not MIT_REAL.is_dir(), reason="shared MIT-Berkeley data not present")
def test_real_mit_berkeley():
    ds = MITDataset(MIT_REAL, objects=["apple"])
    s = ds[0]
    assert s.image.shape == (3, 334, 334) and s.shading.shape == (1, 334, 334)
    assert 0.1 < s.mask.float().mean() < 0.9
    m = s.mask[0]
    assert 0 < s.image[:, m].max() <= 1 and s.reflectance[:, m].min() >= 0
    # the data is linear: diffuse ~ k * reflectance * shading inside the mask
    prod = (s.reflectance * s.shading)[:, m]
    ratio = s.image[:, m].sum() / prod.sum()
    rel = (s.image[:, m] - ratio * prod).abs().mean() / s.image[:, m].mean()
    assert rel < 0.2
