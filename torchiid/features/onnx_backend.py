"""ONNX export of the backbone feature map and an onnxruntime runner.

The exported graph is :class:`~torchiid.features.backbone.FeatureMapExtractor`: input ``image``
``(batch, 3, height, width)`` float32 **sRGB in [0, 1]** (normalisation is inside the graph),
output ``features`` ``(batch, 1280, ceil(height/32), ceil(width/32))``; batch, height and width
are dynamic. The legacy TorchScript exporter (``dynamo=False``) is used, so ``onnxscript`` is not
needed.

Integrity: a model directory (``models/`` in the repository, or the user cache) holds a
``manifest.json`` listing each file's SHA-256, opset, input/output names and the SHA-256 of the
source ``.pth`` weights. :func:`ensure_onnx_model` reuses a cached file only if the manifest entry
was made from the same weights and export settings and the file still has the recorded hash;
otherwise it exports again (never downloads), writing to a temporary file that is moved into
place with :func:`os.replace`, so a half-written model is never used. Exports made with the
same torch and ``onnx`` packages are byte-identical; with other versions the bytes may differ,
which is why the check compares the file against the manifest written beside it rather than
a fixed hash.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from torchiid._version import __version__
from torchiid.core.check import check_image
from torchiid.core.exceptions import ModelError
from torchiid.core.memory import release_free_memory
from torchiid.features.backbone import (
    FEATURE_DIM,
    FeatureMapExtractor,
    efficientnet_lite0,
    file_sha256,
    weights_path,
    weights_sha256,
)

__all__ = [
    "ONNX_FILENAME",
    "OnnxFeatureExtractor",
    "default_cache_dir",
    "ensure_onnx_model",
    "export_feature_extractor",
    "export_to_dir",
    "release_sessions",
]

logger = logging.getLogger(__name__)

ONNX_FILENAME = "efficientnet_lite0_features.onnx"
OPSET = 17
INPUT_NAME = "image"
OUTPUT_NAME = "features"
EXPORT_VERSION = 1  # bump when the architecture or the export settings change
MANIFEST = "manifest.json"
_FILE_MODE = 0o644  # mkstemp creates 0o600 files; exported models are readable by all


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def export_feature_extractor(path: str | Path, opset: int = OPSET) -> dict:
    """Export the pretrained backbone's feature map to ONNX (dynamic batch, height and width).

    The file is written atomically (temporary file + :func:`os.replace`).

    Args:
        path: destination ``.onnx`` file; its directory must exist and be writable.
        opset: ONNX opset version.

    Returns:
        The manifest entry of the file (name, sha256, opset, inputs, outputs, source weights).

    Raises:
        ModelError: the export failed.
    """
    path = Path(path)
    model = FeatureMapExtractor(efficientnet_lite0(pretrained=True)).eval()
    example = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(0))
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        with warnings.catch_warnings():
            # The TorchScript exporter is deprecated in torch >= 2.9 but needs no onnxscript;
            # constant folding cannot fold the stride-2 "SAME" padding slices (harmless).
            warnings.filterwarnings("ignore", category=DeprecationWarning)
            warnings.filterwarnings("ignore", message=".*Constant folding.*")
            torch.onnx.export(
                model,
                (example,),
                tmp,
                dynamo=False,
                opset_version=opset,
                input_names=[INPUT_NAME],
                output_names=[OUTPUT_NAME],
                dynamic_axes={
                    INPUT_NAME: {0: "batch", 2: "height", 3: "width"},
                    OUTPUT_NAME: {0: "batch", 2: "feature_height", 3: "feature_width"},
                },
            )
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except Exception as err:
        Path(tmp).unlink(missing_ok=True)
        raise ModelError(f"ONNX export to {path} failed: {err}") from err
    logger.info("exported ONNX feature extractor to %s", path)
    return {
        "name": path.name,
        "sha256": file_sha256(path),
        "size_bytes": path.stat().st_size,
        "opset": opset,
        "export_version": EXPORT_VERSION,
        "inputs": [
            {
                "name": INPUT_NAME,
                "shape": ["batch", 3, "height", "width"],
                "dtype": "float32",
                "range": "sRGB in [0, 1]",
            }
        ],
        "outputs": [
            {
                "name": OUTPUT_NAME,
                "shape": ["batch", FEATURE_DIM, "ceil(height/32)", "ceil(width/32)"],
                "dtype": "float32",
            }
        ],
        "source_weights": {"name": weights_path().name, "sha256": weights_sha256()},
        "exporter": {"torch": torch.__version__.split("+")[0], "dynamo": False},
        "torchiid_version": __version__,
    }


def _read_manifest(directory: Path) -> dict:
    try:
        manifest = json.loads((directory / MANIFEST).read_text())
    except (OSError, ValueError):
        return {"format": 1, "models": []}
    if not isinstance(manifest, dict) or not isinstance(manifest.get("models"), list):
        return {"format": 1, "models": []}
    return manifest


def export_to_dir(output_dir: str | Path = "models") -> Path:
    """Export the feature extractor into ``output_dir`` and update its ``manifest.json``.

    Backs ``tools/export_onnx.py`` and the ``torchiid export-onnx`` command.

    Returns:
        Path of the exported ``.onnx`` file.
    """
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    path = output_dir / ONNX_FILENAME
    entry = export_feature_extractor(path)
    manifest = _read_manifest(output_dir)
    manifest["models"] = [m for m in manifest["models"] if m.get("name") != entry["name"]]
    manifest["models"].append(entry)
    text = json.dumps(manifest, indent=2, sort_keys=True) + "\n"
    _atomic_write_bytes(output_dir / MANIFEST, text.encode())
    return path


def default_cache_dir() -> Path:
    """Writable cache folder: ``$TORCHIID_CACHE``, else ``~/.cache/torchiid``, else a temp dir."""
    candidates = []
    if os.environ.get("TORCHIID_CACHE"):
        candidates.append(Path(os.environ["TORCHIID_CACHE"]).expanduser())
    candidates.append(Path.home() / ".cache" / "torchiid")
    candidates.append(Path(tempfile.gettempdir()) / "torchiid")
    for directory in candidates:
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(directory, os.W_OK):
            return directory
    raise ModelError(f"no writable cache directory among {[str(c) for c in candidates]}")


def _valid_entry(directory: Path) -> bool:
    path = directory / ONNX_FILENAME
    if not path.is_file():
        return False
    for entry in _read_manifest(directory)["models"]:
        if entry.get("name") != ONNX_FILENAME:
            continue
        return (
            entry.get("opset") == OPSET
            and entry.get("export_version") == EXPORT_VERSION
            and entry.get("source_weights", {}).get("sha256") == weights_sha256()
            and entry.get("sha256") == file_sha256(path)
        )
    return False


def ensure_onnx_model(cache_dir: str | Path | None = None) -> Path:
    """Path of a valid exported feature extractor, exporting it first if needed.

    The file in ``cache_dir`` (default :func:`default_cache_dir`) is reused when the
    ``manifest.json`` beside it records the current weights' SHA-256, opset and export version,
    and the file's SHA-256; otherwise it is exported again (about a second, no download).

    Returns:
        Path of the ``.onnx`` file.
    """
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    if _valid_entry(directory):
        return directory / ONNX_FILENAME
    logger.info("exporting the ONNX feature extractor into %s (first use)", directory)
    return export_to_dir(directory)


@lru_cache(maxsize=4)
def _session(path: str, sha: str, providers: tuple[str, ...], threads: int):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        session = ort.InferenceSession(path, sess_options=options, providers=list(providers))
    except Exception as err:  # onnxruntime raises its own exception types
        raise ModelError(f"onnxruntime cannot load {path}: {err}") from err
    # loading leaves the graph optimiser's freed buffers (about 30 MB) resident in the C heap,
    # under the CNN pass that follows, one of a decomposition's two peaks of memory
    release_free_memory()
    return session


def release_sessions() -> None:
    """Forget the onnxruntime sessions that :class:`OnnxFeatureExtractor` shares.

    See :func:`~torchiid.features.patches.release_feature_extractors`.
    """
    _session.cache_clear()


class OnnxFeatureExtractor:
    """Run the exported backbone feature map with onnxruntime.

    Args:
        path: the ``.onnx`` file; ``None`` uses :func:`ensure_onnx_model`.
        providers: onnxruntime execution providers; ``None`` picks ``CUDAExecutionProvider``
            first when it is available and ``device`` is CUDA, else ``CPUExecutionProvider``.
        device: ``"cpu"``, ``"cuda"`` or ``None`` (CPU).
        intra_op_threads: threads per operator; ``None`` follows ``torch.get_num_threads()``.

    Shape:
        ``(B, 3, H, W)`` sRGB in ``[0, 1]`` -> ``(B, 1280, ceil(H/32), ceil(W/32))``; the
        output has the input's dtype and device (computed in float32).

    Memory: onnxruntime's CPU arena keeps the largest activation buffers of a run (hundreds
    of megabytes for a photo's shared-mode features) for the next one.
    By default each call shrinks it at its end, so that memory is not held through the
    solves that follow Stage 0 (the session and its weights stay cached); a loop of calls
    passes ``release_memory=False`` to all but its last.
    """

    def __init__(
        self,
        path: str | Path | None = None,
        providers: list[str] | None = None,
        device: str | torch.device | None = None,
        intra_op_threads: int | None = None,
    ) -> None:
        import onnxruntime as ort

        self.path = Path(path) if path is not None else ensure_onnx_model()
        if not self.path.is_file():
            raise ModelError(f"ONNX model not found at {self.path}; run `torchiid export-onnx`")
        if providers is None:
            want_cuda = device is not None and torch.device(device).type == "cuda"
            providers = ["CPUExecutionProvider"]
            if want_cuda and "CUDAExecutionProvider" in ort.get_available_providers():
                providers.insert(0, "CUDAExecutionProvider")
        self.providers = tuple(providers)
        self.threads = intra_op_threads or torch.get_num_threads()
        self.session = _session(
            str(self.path), file_sha256(self.path), self.providers, self.threads
        )
        self._shrink = ort.RunOptions()
        self._shrink.add_run_config_entry("memory.enable_memory_arena_shrinkage", "cpu:0")

    def __call__(self, image: torch.Tensor, *, release_memory: bool = True) -> torch.Tensor:
        """Feature map of an sRGB batch; see the class docstring.

        Args:
            image: ``(B, 3, H, W)`` sRGB in ``[0, 1]``.
            release_memory: shrink onnxruntime's CPU arena at the end of the run (the
                values are the same either way).
        """
        check_image(image, "image", channels=3, nonnegative=False)
        x = np.ascontiguousarray(image.detach().to("cpu", torch.float32).numpy())
        options = self._shrink if release_memory else None
        (out,) = self.session.run([OUTPUT_NAME], {INPUT_NAME: x}, options)
        return torch.from_numpy(out).to(device=image.device, dtype=image.dtype)
