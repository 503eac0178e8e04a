"""Writing images: every file is written atomically, with the permissions of a normal file.

The data go to a temporary file in the target folder, which is renamed over the target only
when complete, so an output is never half-written (:func:`write_atomically`). The file gets
the permissions of a normally created file (``0o666`` less the process umask). Encodings:
8-bit sRGB, 16-bit sRGB and 16-bit linear (PNG or TIFF, through OpenCV), float32 ``.npy``, and
float32 OpenEXR (ZIP compression, channel ``Y`` or ``R``, ``G``, ``B``, optional extra header
attributes).
"""

from __future__ import annotations

import os
import tempfile
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from torchiid.core.bands import CACHE_PIXELS, row_bands
from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ImageError
from torchiid.io.exr import exr_attributes, write_exr

__all__ = [
    "Encoding",
    "encode_codes",
    "process_umask",
    "save_codes",
    "save_encoded",
    "save_image",
    "save_uint8",
    "write_atomically",
]

Encoding = Literal["srgb8", "srgb16", "linear16", "npy", "exr"]


def _to_hwc(x: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().to("cpu", torch.float32)
        if x.dim() == 4:
            if x.shape[0] != 1:
                raise ImageError(f"save_image takes one image, got a batch of {x.shape[0]}")
            x = x[0]
        if x.dim() == 3:
            x = x.permute(1, 2, 0)
        x = x.numpy()
    x = np.asarray(x, dtype=np.float32)
    if x.ndim == 3 and x.shape[2] == 1:
        x = x[..., 0]
    return x


def save_image(
    path: str | os.PathLike,
    image: torch.Tensor | np.ndarray,
    encoding: Encoding = "srgb8",
    metadata: Mapping[str, float | str] | None = None,
) -> Path:
    """Write a **linear** image atomically.

    Args:
        path: target file. ``.png`` (or ``.tif``) for the integer encodings, ``.npy`` for
            ``"npy"``, ``.exr`` for ``"exr"``.
        image: linear values, ``(3, H, W)``/``(1, 3, H, W)``/``(1, H, W)`` tensor or
            ``(H, W[, 3])`` array.
        encoding: ``"srgb8"`` (viewable 8-bit sRGB PNG, values clipped to [0, 1]),
            ``"srgb16"`` (16-bit sRGB), ``"linear16"`` (16-bit linear, clipped to [0, 1]),
            ``"npy"`` (float32 linear, unclipped, channel-last) or ``"exr"`` (OpenEXR, float32
            linear, unclipped, ZIP-compressed; channel ``Y`` for a gray image, ``R``, ``G``,
            ``B`` for colour).
        metadata: extra OpenEXR header attributes (``"exr"`` only): numbers are stored as
            double attributes, strings as string attributes; :func:`read_exr` returns them.

    Returns:
        The written path.

    Raises:
        ValueError: unknown encoding, or ``metadata`` with another encoding than ``"exr"`` or
            with a reserved key or a value that is neither a number nor a string.
        ImageError: the image has an unusable shape, or the encoder fails.
    """
    path = Path(path)
    if metadata and encoding != "exr":
        raise ValueError(f"{path}: metadata can only be stored with encoding='exr'")
    arr = _to_hwc(image)
    if encoding == "exr":
        if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)):
            raise ImageError(f"{path}: an OpenEXR image must be gray or RGB, got {arr.shape}")
        attributes = exr_attributes(path, metadata or {})
        write_atomically(path, lambda tmp: write_exr(tmp, path, arr, attributes))
        return path
    if encoding == "npy":
        _atomic_write(path, arr, npy=True)
        return path
    if encoding not in ("srgb8", "srgb16", "linear16"):
        raise ValueError(f"unknown encoding {encoding!r}; use srgb8, srgb16, linear16, npy or exr")
    if arr.ndim not in (2, 3):
        raise ImageError(f"{path}: a picture is (H, W) or (H, W, C), got shape {arr.shape}")
    payload = np.empty(arr.shape, np.uint8 if encoding == "srgb8" else np.uint16)
    # a band of rows at a time: the encoding's steps then read back what the one before wrote
    # from the CPU's caches, not from memory
    for rows in row_bands(arr.shape[0], arr.shape[1], CACHE_PIXELS):
        codes = _codes(arr[rows], encoding)
        payload[rows] = codes[..., ::-1] if codes.ndim == 3 else codes  # RGB -> BGR for OpenCV
    _atomic_write(path, payload)
    return path


def _codes(arr: np.ndarray, encoding: Encoding) -> np.ndarray:
    """The integer codes of linear values for ``srgb8``, ``srgb16`` or ``linear16``."""
    lin = np.clip(arr, 0, 1)
    if encoding in ("srgb8", "srgb16"):
        lin = linear_to_srgb(torch.from_numpy(lin)).numpy()
    if encoding == "srgb8":
        return np.round(lin * 255).astype(np.uint8)
    return np.round(lin * 65535).astype(np.uint16)


def save_uint8(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` or ``(H, W)`` uint8 picture (already sRGB) atomically as is."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8:
        raise ImageError(f"save_uint8 takes an (H, W[, 3]) uint8 array, got {rgb.dtype}")
    return save_codes(path, rgb)


def save_codes(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` RGB or ``(H, W)`` gray uint8 / uint16 array atomically as is.

    The codes are written unchanged (no colour encoding), e.g. a 16-bit linear PNG whose
    codes the caller computed.
    """
    payload = _code_payload(rgb, "save_codes")
    path = Path(path)
    _atomic_write(path, payload)
    return path


def encode_codes(rgb: np.ndarray, suffix: str = ".png") -> np.ndarray:
    """The encoded file of an ``(H, W, 3)`` RGB or ``(H, W)`` gray uint8 / uint16 array.

    As :func:`save_codes` encodes it (OpenCV, by ``suffix``), as a byte buffer for
    :func:`save_encoded`: the encoding releases the GIL, so several files can be encoded at
    once in threads while their writing stays in order.
    """
    ok, buf = cv2.imencode(suffix, _code_payload(rgb, "encode_codes"))
    if not ok:
        raise ImageError(f"OpenCV cannot encode a {suffix} file")
    return buf


def _code_payload(rgb: np.ndarray, who: str) -> np.ndarray:
    """``rgb`` checked and in OpenCV's channel order (BGR), for :func:`save_codes` and co."""
    rgb = np.asarray(rgb)
    if rgb.dtype not in (np.uint8, np.uint16) or rgb.ndim not in (2, 3):
        raise ImageError(
            f"{who} takes an (H, W[, 3]) uint8 or uint16 array, got {rgb.dtype} {rgb.shape}"
        )
    if rgb.ndim == 3 and rgb.shape[2] != 3:
        raise ImageError(f"{who} takes 3 colour channels, got {rgb.shape[2]}")
    return np.ascontiguousarray(rgb[..., ::-1]) if rgb.ndim == 3 else rgb


def save_encoded(path: str | os.PathLike, encoded: np.ndarray | bytes) -> Path:
    """Write an encoded file (:func:`encode_codes`) atomically as is."""
    path = Path(path)

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(memoryview(encoded))

    write_atomically(path, write)
    return path


def _write_npy(tmp: str, arr: np.ndarray) -> None:
    with open(tmp, "wb") as fh:
        np.save(fh, arr)


def _write_encoded(tmp: str, path: Path, payload: np.ndarray) -> None:
    ok, buf = cv2.imencode(path.suffix or ".png", payload)
    if not ok:
        raise ImageError(f"{path}: OpenCV cannot encode a {path.suffix} file")
    with open(tmp, "wb") as fh:
        fh.write(buf.tobytes())


_umask_lock = threading.Lock()
_probed_umask: int | None = None


def process_umask() -> int:
    """The process umask, read without changing it where the system shows it (Linux)."""
    global _probed_umask
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_lock:  # elsewhere: set and restore it, once; 0o077 is the safe value meanwhile
        if _probed_umask is None:
            _probed_umask = os.umask(0o077)
            os.umask(_probed_umask)
        return _probed_umask


def _atomic_write(path: Path, payload: np.ndarray, npy: bool = False) -> None:
    """Write ``payload`` atomically: as ``.npy`` if ``npy``, else encoded by ``path``'s suffix."""
    if npy:
        write_atomically(path, lambda tmp: _write_npy(tmp, payload))
    else:
        write_atomically(path, lambda tmp: _write_encoded(tmp, path, payload))


def write_atomically(path: Path, write: Callable[[str], None]) -> None:
    """Let ``write`` fill a temporary file in the target folder, then rename it over ``path``.

    The temporary file (created ``0o600``) gets the mode of a normally created file,
    ``0o666`` less the umask, before the rename.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~process_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
