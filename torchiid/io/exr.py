"""OpenEXR: float images with channels ``Y`` or ``R``, ``G``, ``B`` (and ``A``) and metadata.

OpenEXR is the interchange format for linear HDR images; torchiid reads half or float flat
images (:func:`read_exr`) and writes float32 ones with ZIP compression and extra header
attributes (:func:`write_exr`, through :func:`~torchiid.io.write.save_image`).
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from torchiid.core.exceptions import ImageError
from torchiid.io.files import EXR_MAGIC, check_file, damaged, fail, one_line, read_head

__all__ = ["EXR_LAYOUT", "exr_attributes", "exr_pixels", "read_exr", "write_exr"]

# Header attributes that describe the file's layout: not returned as metadata, not writable.
EXR_LAYOUT = frozenset(
    {
        "channels",
        "chunkCount",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "name",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "tiles",
        "type",
        "version",
    }
)


def read_exr(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, Any]]:
    """Read an OpenEXR file's pixels and metadata.

    Only the first part of a multi-part file is returned, and only its data window.

    Args:
        path: an OpenEXR file with a channel ``Y`` (gray) or channels ``R``, ``G``, ``B``
            (colour), optionally ``A``; half or float pixels.

    Returns:
        The float32 pixels — ``(H, W)`` for ``Y``, ``(H, W, 3)`` for ``R``, ``G``, ``B``, with
        ``A`` appended as a last channel where present (``(H, W, 2)`` or ``(H, W, 4)``) — and the
        header attributes other than the layout ones (``channels``, ``compression``,
        ``dataWindow``, ...): double attributes as :class:`float`, strings as :class:`str`,
        others as the ``OpenEXR`` package gives them.

    Raises:
        ImageError: the file is missing, unreadable, not an OpenEXR file, truncated or corrupt,
            deep, or has other channels.
    """
    path = Path(path)
    check_file(path)
    if not read_head(path).startswith(EXR_MAGIC):
        raise fail(path, "is not an OpenEXR file")
    return exr_pixels(path)


def exr_pixels(path: Path) -> tuple[np.ndarray, dict[str, Any]]:
    """:func:`read_exr` of a file already known to be there and to start like an OpenEXR file."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            if not exr.parts:  # the binding skips a part whose pixels it cannot decode
                raise damaged(path, "OpenEXR cannot decode its pixel data")
            header = dict(exr.header())
            channels = dict(exr.channels())
    except ImageError:
        raise
    except Exception as exc:  # noqa: BLE001 - the binding raises RuntimeError, ValueError, ...
        raise fail(path, f"is not a readable OpenEXR file ({one_line(exc)})") from None
    if header.get("type") in (OpenEXR.deepscanline, OpenEXR.deeptile):
        raise fail(path, "is a deep OpenEXR file; expected a flat image")
    names = set(channels)
    if {"R", "G", "B"} <= names:
        wanted = ["R", "G", "B"]
    elif "Y" in names and not names & {"RY", "BY"}:
        wanted = ["Y"]
    else:
        raise fail(path, f"has OpenEXR channels {sorted(names)}; expected Y or R, G, B")
    if "A" in names:
        wanted.append("A")
    planes = []
    for name in wanted:
        channel = channels[name]
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise fail(path, f"has a subsampled OpenEXR channel {name}; expected full size")
        if channel.pixels.dtype.kind != "f":
            raise fail(path, f"has {channel.pixels.dtype} OpenEXR channel {name}; expected float")
        planes.append(channel.pixels)
    if len(planes) == 1:
        arr = planes[0].astype(np.float32, copy=False)
    else:
        arr = np.stack(planes, axis=-1).astype(np.float32, copy=False)
    metadata = {}
    for key, value in header.items():
        if key in EXR_LAYOUT:
            continue
        if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.size == 1:
            value = float(value.reshape(()))  # the binding's form of a double attribute
        metadata[key] = value
    return arr, metadata


def exr_attributes(path: Path, metadata: Mapping[str, float | str]) -> dict[str, Any]:
    """Header attributes for ``metadata``: numbers as double attributes, strings as strings."""
    attributes: dict[str, Any] = {}
    for key, value in metadata.items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"{path}: metadata keys must be non-empty strings, got {key!r}")
        if key in EXR_LAYOUT:
            raise ValueError(f"{path}: metadata key {key!r} is a reserved OpenEXR attribute")
        if isinstance(value, str):
            attributes[key] = value
        elif isinstance(value, numbers.Real) and not isinstance(value, bool):
            # a 1-element float64 array is how the OpenEXR binding writes a double attribute
            attributes[key] = np.array([float(value)], np.float64)
        else:
            raise ValueError(
                f"{path}: metadata {key!r} must be a float or a str, got {type(value).__name__}"
            )
    return attributes


def _use_threads(openexr: Any) -> None:
    """Let OpenEXR compress a file's blocks of lines on as many threads as torch uses."""
    import torch

    threads = torch.get_num_threads()
    want = threads if threads > 1 else 0  # 0: on the calling thread
    if want != openexr.global_thread_count():
        openexr.set_global_thread_count(want)


def write_exr(tmp: str, path: Path, arr: np.ndarray, attributes: dict[str, Any]) -> None:
    """Write ``arr`` (gray ``(H, W)`` or ``(H, W, 3)``) to ``tmp``; errors name ``path``."""
    import OpenEXR

    if arr.ndim == 2:
        channels = {"Y": np.ascontiguousarray(arr, np.float32)}
    else:
        channels = {name: np.ascontiguousarray(arr[..., i]) for i, name in enumerate("RGB")}
    _use_threads(OpenEXR)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes)
    try:
        with OpenEXR.File(header, channels) as exr:
            exr.write(tmp)
    except OSError:
        raise
    except Exception as exc:  # noqa: BLE001 - the binding raises RuntimeError, ValueError, ...
        raise ImageError(f"{path}: OpenEXR cannot write the file ({one_line(exc)})") from None
