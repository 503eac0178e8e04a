"""Decoding: an image file's array as stored, its orientation, and what the decoders said.

8-bit and 16-bit PNG / JPEG / TIFF / BMP / WebP files are decoded with OpenCV's
``IMREAD_UNCHANGED`` so no bit depth is lost; OpenEXR files through the ``OpenEXR`` package
(:mod:`torchiid.io.exr`) and ``.npy`` arrays with numpy. Every file's structure is checked
first (:mod:`torchiid.io.damage`). What the C decoders print to stderr is collected and logged
(``torchiid -v`` shows it), not left on the terminal beside torchiid's one-line error.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from torchiid.io.damage import JPEG_DAMAGE, check_structure
from torchiid.io.exr import exr_pixels
from torchiid.io.files import check_file, damaged, fail, file_bytes, one_line, read_head, sniff

__all__ = ["Decoded", "declared_size", "decoder_messages", "read_array", "rgb_planes"]

log = logging.getLogger(__name__)

_stderr_lock = threading.Lock()


@contextlib.contextmanager
def decoder_messages() -> Iterator[list[str]]:
    """Collect the lines C decoders print to stderr (file descriptor 2) during the block.

    libjpeg and libpng report damaged data only there, and OpenCV's log writes there too;
    a damaged file is reported once, in torchiid's one-line error, and the rest is logged
    (``torchiid -v`` shows it). The list is filled when the block ends. Decodes in several
    threads take turns here; if stderr cannot be redirected, nothing is collected.
    """
    messages: list[str] = []
    with _stderr_lock:
        try:
            saved = os.dup(2)
        except OSError:
            yield messages
            return
        try:
            with tempfile.TemporaryFile() as capture:
                with contextlib.suppress(Exception):
                    sys.stderr.flush()
                os.dup2(capture.fileno(), 2)
                try:
                    yield messages
                finally:
                    os.dup2(saved, 2)
                    capture.seek(0)
                    text = capture.read().decode("utf-8", "replace")
                    messages.extend(line.strip() for line in text.splitlines() if line.strip())
        finally:
            os.close(saved)


class Decoded(NamedTuple):
    """A file's pixels as stored (:func:`read_array`)."""

    arr: np.ndarray  # (H, W[, C]) as stored in the file, before orientation
    orientation: int
    bgr: bool  # colour channels in OpenCV's BGR(A) order


_PIL_LOCK = threading.Lock()


def declared_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """The ``(height, width)`` a file's header declares, read without decoding its pixels.

    What the memory check needs before a file is decoded: a small file may declare a picture
    that takes gigabytes once decoded. The orientation is not applied (it does not change the
    number of pixels). ``None`` when the header cannot tell; :func:`read_array` then reports
    what is wrong with the file.
    """
    path = Path(path)
    try:
        if path.suffix.lower() == ".npy":
            shape = np.load(path, mmap_mode="r", allow_pickle=False).shape
            return (int(shape[0]), int(shape[1])) if len(shape) >= 2 else None
        if sniff(read_head(path)) == "exr":
            import OpenEXR

            with OpenEXR.File(str(path), header_only=True) as exr:
                (x0, y0), (x1, y1) = exr.header()["dataWindow"]
            return int(y1 - y0 + 1), int(x1 - x0 + 1)
        from PIL import Image

        with _PIL_LOCK:  # Pillow's guard against large headers is a module setting
            guard, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                # what Pillow says of a damaged header (corrupt EXIF, ...) is not the user's
                # business here: decoding reports the damage in one line
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    with Image.open(path) as im:
                        width, height = im.size
            finally:
                Image.MAX_IMAGE_PIXELS = guard
        return int(height), int(width)
    except Exception:  # noqa: BLE001 - any file the header does not describe: decoding tells
        return None


def read_array(path: Path) -> Decoded:
    """The array of an image file as stored, checked for damage, with its EXIF orientation.

    Raises:
        ImageError: the file is missing, unreadable, empty, damaged or not an image.
    """
    check_file(path)
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise fail(path, f"is not a readable .npy array ({exc})") from None
        if arr.dtype.kind not in "fiu":
            raise fail(path, f"holds a {arr.dtype} array, expected numbers")
        return Decoded(arr, 1, False)
    kind = sniff(read_head(path))
    if kind == "exr":
        arr, _ = exr_pixels(path)
        return Decoded(arr, 1, False)
    with file_bytes(path) as data:
        orientation, patch = check_structure(path, kind, data)
        buf = np.frombuffer(data, np.uint8)
        if patch is not None and orientation != 1:
            # OpenCV's TIFF decoder applies (some) orientations itself, depending on its
            # version; decode a copy tagged "1" and apply the orientation here like for the
            # other formats.
            buf = buf.copy()
            at, dtype = patch
            buf[at : at + np.dtype(dtype).itemsize] = np.array([1], dtype).view(np.uint8)
        try:
            with decoder_messages() as messages:
                arr = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        except cv2.error as exc:
            if "CV_IO_MAX_IMAGE_PIXELS" in str(exc):  # OpenCV's cap on a header's pixel count
                raise fail(
                    path,
                    "declares more pixels than OpenCV decodes (2^30 by default; the environment "
                    "variable OPENCV_IO_MAX_IMAGE_PIXELS raises the cap)",
                ) from None
            raise fail(path, f"is not an image OpenCV can decode ({one_line(exc)})") from None
        finally:
            del buf
    for message in messages:
        log.info("%s: the decoder says: %s", path, message)
    if kind == "jpeg" and arr is not None:
        damage = next((m for m in messages if JPEG_DAMAGE.search(m)), None)
        if damage is not None:
            raise damaged(path, f"libjpeg: {damage}")
    if arr is None:
        raise fail(path, "is not an image OpenCV can decode (corrupt or unsupported format)")
    return Decoded(arr, orientation, arr.ndim == 3 and arr.shape[2] >= 3)


def rgb_planes(decoded: Decoded) -> list[np.ndarray]:
    """The ``(H, W)`` channel planes in RGB(A) order, not yet oriented."""
    arr = decoded.arr
    if arr.ndim == 2:
        return [arr]
    if decoded.bgr and arr.dtype in (np.uint8, np.uint16, np.float32):
        planes = list(cv2.split(arr))  # contiguous planes, the fastest input for cv2.LUT
    else:
        planes = [arr[..., i] for i in range(arr.shape[2])]
    if decoded.bgr:
        planes[:3] = planes[2::-1]
    return planes
