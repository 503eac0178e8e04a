import json

import numpy as np
import pytest
import torch

import torchiid
from torchiid.core.exceptions import ModelError
from torchiid.features import onnx_backend
from torchiid.features.backbone import FeatureMapExtractor, efficientnet_lite0, weights_sha256
from torchiid.features.onnx_backend import (
    ONNX_FILENAME,
    OnnxFeatureExtractor,
    default_cache_dir,
    ensure_onnx_model,
)

# Shared with tests/features/test_patches.py through the manifest: one export per session.
TOL = 1e-4  # max abs difference; features lie in [0, 6] (ReLU6)


@pytest.fixture(scope="module")
def torch_extractor():
    return FeatureMapExtractor(efficientnet_lite0()).eval()


def _sha(path):
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_manifest_records_file_and_weights(onnx_path):
    manifest = json.loads((onnx_path.parent / "manifest.json").read_text())
    (entry,) = [m for m in manifest["models"] if m["name"] == ONNX_FILENAME]
    assert entry["sha256"] == _sha(onnx_path)
    assert entry["source_weights"]["sha256"] == weights_sha256()
    assert [i["name"] for i in entry["inputs"]] == ["image"]
    assert [o["name"] for o in entry["outputs"]] == ["features"]
    assert entry["opset"] == onnx_backend.OPSET
    assert entry["torchiid_version"] == torchiid.__version__
    assert not [p for p in onnx_path.parent.iterdir() if p.name.endswith(".tmp")]


def test_cached_model_is_reused(onnx_path, monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("should not export again")

    monkeypatch.setattr(onnx_backend, "export_to_dir", fail)
    assert ensure_onnx_model(onnx_path.parent) == onnx_path


def test_corrupt_or_stale_model_is_exported_again(onnx_path, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(onnx_backend, "export_to_dir", lambda d: calls.append(d) or d)
    (tmp_path / ONNX_FILENAME).write_bytes(onnx_path.read_bytes()[:-10])
    (tmp_path / "manifest.json").write_text((onnx_path.parent / "manifest.json").read_text())
    ensure_onnx_model(tmp_path)  # truncated file: hash mismatch
    (tmp_path / ONNX_FILENAME).write_bytes(onnx_path.read_bytes())
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["models"][0]["source_weights"]["sha256"] = "0" * 64
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    ensure_onnx_model(tmp_path)  # other weights
    ensure_onnx_model(tmp_path / "empty")  # missing
    assert calls == [tmp_path, tmp_path, tmp_path / "empty"]


@pytest.mark.parametrize("shape", [(2, 3, 64, 96), (1, 3, 77, 101), (3, 3, 33, 130)])
def test_onnxruntime_matches_torch(onnx_path, torch_extractor, shape):
    x = torch.rand(*shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref = torch_extractor(x)
    out = OnnxFeatureExtractor(onnx_path)(x)
    assert out.shape == ref.shape
    assert (out - ref).abs().max() < TOL


def test_output_follows_input_dtype(onnx_path):
    x = torch.rand(1, 3, 40, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    extractor = OnnxFeatureExtractor(onnx_path, intra_op_threads=1)
    out = extractor(x)
    assert out.dtype == torch.float64 and out.device == x.device
    np.testing.assert_allclose(out.numpy(), extractor(x.float()).double().numpy())
    assert extractor.providers == ("CPUExecutionProvider",)


def test_release_memory_asks_onnxruntime_to_shrink_its_arena(onnx_path):
    # what the shrink gives back is measured by tools/bench_onnx_memory.py; here: that it is asked
    x = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    extractor = OnnxFeatureExtractor(onnx_path, intra_op_threads=1)
    session, options = extractor.session, []

    class Recording:
        def run(self, names, feeds, run_options=None):
            options.append(run_options)
            return session.run(names, feeds, run_options)

    extractor.session = Recording()
    kept = extractor(x, release_memory=False)
    released = extractor(x)  # the default
    assert torch.equal(released, kept)
    assert options[0] is None
    key = "memory.enable_memory_arena_shrinkage"
    assert options[1].get_run_config_entry(key) == "cpu:0"


def test_a_new_session_hands_back_the_memory_its_loading_freed(onnx_path, monkeypatch):
    """onnxruntime's graph optimiser frees about 30 MB that would stay resident under the pass."""
    import onnxruntime as ort

    events = []
    real_session = ort.InferenceSession

    def session(*args, **kwargs):
        made = real_session(*args, **kwargs)
        events.append("session")
        return made

    monkeypatch.setattr(ort, "InferenceSession", session)
    monkeypatch.setattr(onnx_backend, "release_free_memory", lambda: events.append("release"))
    # a thread count no other test uses: a session of its own, not one the cache kept
    key = (str(onnx_path), _sha(onnx_path), ("CPUExecutionProvider",), 7)
    made = onnx_backend._session(*key)
    assert events == ["session", "release"]  # after the session is made, once
    assert onnx_backend._session(*key) is made  # the kept session: nothing loaded or released
    assert events == ["session", "release"]


def test_missing_model_raises(tmp_path):
    with pytest.raises(ModelError, match="ONNX model not found"):
        OnnxFeatureExtractor(tmp_path / "missing.onnx")


def test_default_cache_dir_honours_env(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHIID_CACHE", str(tmp_path / "cache"))
    assert default_cache_dir() == tmp_path / "cache"
    assert (tmp_path / "cache").is_dir()


@pytest.mark.slow
def test_exports_are_byte_identical(onnx_path, tmp_path):
    entry = onnx_backend.export_feature_extractor(tmp_path / ONNX_FILENAME)
    assert entry["sha256"] == _sha(onnx_path)
