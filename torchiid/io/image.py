"""The one image loader and saver of torchiid.

Reading (:func:`load_image`, :func:`load_mask`, :func:`read_exr`):

* 8-bit and 16-bit PNG / JPEG / TIFF / BMP / WebP files are decoded with OpenCV's
  ``IMREAD_UNCHANGED`` so no bit depth is lost; values are scaled by 255 or 65535 to ``[0, 1]``.
* The EXIF Orientation tag (values 1-8) of JPEG, PNG, TIFF and WebP files is applied, so the
  array is the picture as viewers show it (the same result as Pillow's
  ``ImageOps.exif_transpose``); :attr:`LoadedImage.orientation` tells which value was found.
* Float files (32-bit float TIFF, OpenEXR ``.exr`` with channels ``Y`` or ``R``, ``G``, ``B``
  and optionally ``A``, half or float; ``.npy`` arrays of shape ``(H, W)``, ``(H, W, 3)`` or
  ``(H, W, 4)``) are taken as they are.
* Colour encoding: integer files are sRGB-encoded unless ``linear=True`` (the CLI's
  ``--linear``) and are decoded through a lookup table of the exact IEC 61966-2-1 curve; float
  files are linear. The returned image is always **linear RGB**.
* Gray files are promoted to RGB; an alpha channel is, by default, used as a mask
  (``alpha > 0.5`` is inside) — pass ``alpha="error"`` to reject it or ``alpha="ignore"``.
* Damaged files are rejected, never returned with filler: a JPEG's marker structure must be
  complete up to the end-of-image marker of its main image (bytes after it, such as the
  video of a motion photo, MPF / gain-map images or padding, are allowed); every PNG chunk must
  lie inside the file, critical chunks must match their CRC-32, and the IEND chunk must be
  there; WebP RIFF chunks and the TIFF strips or tiles of the first image must lie inside the
  file; OpenEXR pixel data must decode. While a JPEG decodes, libjpeg's reports of damaged
  data (premature end of a data segment, bad Huffman code, ...), which it would otherwise
  paper over with gray filler or garbled blocks, reject the file too. A JPEG has no checksum,
  so altered bytes inside its compressed data that still decode cleanly cannot be detected.
* What the C decoders print to stderr is collected and logged (``torchiid -v`` shows it),
  not left on the terminal beside torchiid's one-line error.
* Bad files raise :class:`~torchiid.core.exceptions.ImageError` with a one-line message naming
  the file and the problem: missing, unreadable, empty, not an image, truncated or corrupt,
  zero size, smaller than ``min_side`` pixels, or containing NaN / infinity.

Writing (:func:`save_image`, :func:`save_uint8`, :func:`save_codes`, :func:`save_encoded`) is
atomic: the data go to a temporary file in the target folder, which is renamed over the target
only when complete, so an output is never half-written. The file gets the permissions of a
normally created file (``0o666`` less the process umask). Encodings: 8-bit sRGB, 16-bit sRGB
and 16-bit linear (PNG or TIFF, through OpenCV), float32 ``.npy``, and float32 OpenEXR (ZIP
compression, channel ``Y`` or ``R``, ``G``, ``B``, optional extra header attributes).
"""

from __future__ import annotations

import contextlib
import logging
import mmap
import numbers
import os
import re
import struct
import sys
import tempfile
import threading
import zlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple

import cv2
import numpy as np
import torch
from PIL import Image

from torchiid.core.check import MIN_SIDE
from torchiid.core.colour import decode_lut, linear_to_srgb, srgb_to_linear
from torchiid.core.exceptions import ImageError

__all__ = [
    "LoadedImage",
    "load_image",
    "load_mask",
    "read_exr",
    "save_image",
    "save_uint8",
    "save_codes",
    "encode_codes",
    "save_encoded",
    "srgb_to_linear",
    "linear_to_srgb",
]

log = logging.getLogger(__name__)

Encoding = Literal["srgb8", "srgb16", "linear16", "npy", "exr"]


@dataclass(frozen=True)
class LoadedImage:
    """An image read from disk.

    Attributes:
        image: ``(3, H, W)`` float32 **linear** RGB in ``[0, 1]`` (float files may exceed 1),
            upright: the EXIF orientation is already applied.
        mask: ``(1, H, W)`` bool from the alpha channel, or ``None``.
        path: the file it came from.
        bit_depth: 8, 16 or 32 (float, including half-float OpenEXR).
        linear_file: whether the file's values were taken as linear (no sRGB decoding).
        orientation: the EXIF Orientation value (1-8) that was applied; 1 when the file has
            none.
    """

    image: torch.Tensor
    mask: torch.Tensor | None
    path: Path
    bit_depth: int
    linear_file: bool
    orientation: int = 1


# ---------------------------------------------------------------------------------------------
# Reading


def _fail(path: Path, problem: str) -> ImageError:
    return ImageError(f"{path}: {problem}")


def _damaged(path: Path, detail: str) -> ImageError:
    return _fail(path, f"is truncated or corrupt ({detail})")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _check_file(path: Path) -> None:
    if not path.exists():
        raise _fail(path, "no such file")
    if path.is_dir():
        raise _fail(path, "is a directory, not an image file")
    if not os.access(path, os.R_OK):
        raise _fail(path, "cannot be read (permission denied)")
    if path.stat().st_size == 0:
        raise _fail(path, "is empty (0 bytes)")


def _read_head(path: Path, n: int = 16) -> bytes:
    try:
        with open(path, "rb") as fh:
            return fh.read(n)
    except OSError as exc:
        raise _fail(path, f"cannot be read ({_one_line(exc)})") from None


@contextlib.contextmanager
def _mapped(path: Path) -> Iterator[mmap.mmap | bytes]:
    """The file's bytes, memory-mapped read-only where possible (no copy in memory)."""
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise _fail(path, f"cannot be read ({_one_line(exc)})") from None
    with fh:
        try:
            mapped: mmap.mmap | None = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError):  # a file system without mmap: read it instead
            mapped = None
        if mapped is None:
            yield fh.read()
            return
        try:
            yield mapped
        finally:
            with contextlib.suppress(BufferError):  # a view is still referenced: GC closes it
                mapped.close()


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_EXR_MAGIC = b"\x76\x2f\x31\x01"


def _sniff(head: bytes) -> str:
    if head.startswith(b"\xff\xd8"):
        return "jpeg"
    if head.startswith(_PNG_SIGNATURE):
        return "png"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "webp"
    if head.startswith(_EXR_MAGIC):
        return "exr"
    return "other"


# Where the entropy-coded data of a JPEG scan ends: 0xFF followed by a byte that is not a stuffed
# zero, a restart marker (RST0-7) or another fill 0xFF.
_JPEG_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _check_jpeg(path: Path, data: mmap.mmap | bytes) -> bytes | None:
    """Walk the markers of a JPEG up to its main image's EOI; return the EXIF payload.

    Bytes after that EOI are allowed: phones and cameras append motion-photo videos, MPF
    (multi-picture, HDR gain map) images, maker trailers and padding there.

    Raises:
        ImageError: the structure ends before the EOI, or is broken.
    """
    n = len(data)
    pos, exif, frame, scan = 2, None, False, False
    while True:
        pos = data.find(b"\xff", pos)  # like libjpeg, skip stray bytes before a marker
        if pos < 0:
            raise _damaged(path, "the file ends before its JPEG end-of-image marker")
        while pos < n and data[pos] == 0xFF:
            pos += 1
        if pos >= n:
            raise _damaged(path, "the file ends before its JPEG end-of-image marker")
        marker = data[pos]
        pos += 1
        if marker == 0xD9:
            if not scan:
                raise _damaged(path, "JPEG end-of-image marker before any image data")
            return exif
        if marker == 0xD8:
            raise _damaged(path, f"second JPEG start-of-image marker at byte {pos - 2}")
        if marker == 0x00 or marker == 0x01 or 0xD0 <= marker <= 0xD7:
            continue  # stuffed byte in garbage, TEM or a stray RSTn: no length field
        if pos + 2 > n:
            raise _damaged(path, "the file ends inside a JPEG marker segment")
        end = pos + ((data[pos] << 8) | data[pos + 1])
        if end < pos + 2:
            raise _damaged(path, f"JPEG marker segment of length < 2 at byte {pos - 2}")
        if end > n:
            raise _damaged(path, "the file ends inside a JPEG marker segment")
        if marker == 0xE1 and exif is None and data[pos + 2 : pos + 8] == b"Exif\x00\x00":
            exif = bytes(data[pos + 2 : end])
        frame = frame or marker in _JPEG_SOF
        pos = end
        if marker == 0xDA:  # start of scan: skip its entropy-coded data
            if not frame:
                raise _damaged(path, "JPEG scan before any frame header")
            scan = True
            found = _JPEG_SCAN_END.search(data, pos)
            if found is None:
                raise _damaged(path, "the file ends inside the JPEG image data")
            pos = found.start()


def _check_png(path: Path, data: mmap.mmap | bytes) -> bytes | None:
    """Walk the chunks of a PNG up to IEND, checking the CRC-32s; return the eXIf payload.

    An ancillary chunk with a wrong CRC is ignored, as libpng does; a critical one (IHDR,
    PLTE, IDAT, IEND) makes the file corrupt.

    Raises:
        ImageError: a chunk runs past the end of the file, a critical chunk's CRC is wrong, or
            IEND is missing.
    """
    n = len(data)
    pos, exif = len(_PNG_SIGNATURE), None
    with memoryview(data) as view:
        while True:
            if pos + 12 > n:
                raise _damaged(path, "the file ends before the PNG IEND chunk")
            length = int.from_bytes(view[pos : pos + 4], "big")
            kind = bytes(view[pos + 4 : pos + 8])
            name = kind.decode("latin-1") if kind.isalpha() else f"0x{kind.hex()}"
            end = pos + 12 + length
            if length > 0x7FFFFFFF:
                raise _damaged(path, f"PNG chunk length {length} at byte {pos}")
            if end > n:
                raise _damaged(path, f"the file ends inside the PNG {name} chunk")
            if pos == len(_PNG_SIGNATURE) and kind != b"IHDR":
                raise _damaged(path, f"the first PNG chunk is {name}, not IHDR")
            critical = not (kind[0] & 0x20)
            if critical or (kind == b"eXIf" and exif is None):
                crc_ok = zlib.crc32(view[pos + 4 : end - 4]) == int.from_bytes(
                    view[end - 4 : end], "big"
                )
                if critical and not crc_ok:
                    raise _damaged(path, f"CRC mismatch in the PNG {name} chunk at byte {pos}")
                if kind == b"eXIf" and crc_ok:
                    exif = bytes(view[pos + 8 : end - 4])
            if kind == b"IEND":
                return exif
            pos = end


def _check_webp(path: Path, data: mmap.mmap | bytes) -> bytes | None:
    """Check that the RIFF chunks of a WebP file lie inside it; return the EXIF payload."""
    n = len(data)
    riff_end = 8 + int.from_bytes(data[4:8], "little")
    if riff_end > n:
        raise _damaged(path, f"the WebP data should be {riff_end} bytes, the file has {n}")
    pos, exif = 12, None
    while pos + 8 <= riff_end:
        size = int.from_bytes(data[pos + 4 : pos + 8], "little")
        end = pos + 8 + size
        if end > riff_end:
            raise _damaged(path, f"the WebP chunk at byte {pos} runs past the end of the data")
        if data[pos : pos + 4] == b"EXIF" and exif is None:
            exif = bytes(data[pos + 8 : end])
        pos = end + (size & 1)
    return exif


_TIFF_TYPES = {1: "u1", 3: "u2", 4: "u4", 16: "u8"}  # BYTE, SHORT, LONG, LONG8


def _check_tiff(path: Path, data: mmap.mmap | bytes) -> tuple[int, tuple[int, str] | None]:
    """Read the first image directory of a TIFF (classic or BigTIFF).

    Returns:
        The Orientation value (1 when absent or out of 1-8) and, when the tag is present, the
        byte offset and numpy dtype of its value in the file.

    Raises:
        ImageError: the directory, or a strip or tile of the first image, lies past the end of
            the file.
    """
    n = len(data)
    order = "<" if data[:2] == b"II" else ">"
    big = data[2:4] in (b"+\x00", b"\x00+")
    count_fmt, entry_size, field = ("Q", 20, 8) if big else ("H", 12, 4)
    try:
        (ifd,) = struct.unpack_from(order + ("Q" if big else "I"), data, 8 if big else 4)
        (count,) = struct.unpack_from(order + count_fmt, data, ifd)
        first = ifd + struct.calcsize(count_fmt)
        if first + count * entry_size > n:
            raise struct.error("directory past the end")
        entries = {}
        for i in range(count):
            at = first + i * entry_size
            tag, kind = struct.unpack_from(order + "HH", data, at)
            (number,) = struct.unpack_from(order + ("Q" if big else "I"), data, at + 4)
            entries[tag] = (kind, number, at + 4 + field)
    except struct.error:
        raise _damaged(path, "the TIFF image directory lies past the end of the file") from None

    def values(tag: int) -> tuple[np.ndarray | None, int]:
        if tag not in entries or entries[tag][0] not in _TIFF_TYPES:
            return None, 0
        kind, number, at = entries[tag]
        dtype = np.dtype(order + _TIFF_TYPES[kind])
        if number * dtype.itemsize > field:  # the field holds an offset to the values
            (at,) = struct.unpack_from(order + ("Q" if big else "I"), data, at)
        if at + number * dtype.itemsize > n:
            raise _damaged(path, f"the values of TIFF tag {tag} lie past the end of the file")
        return np.frombuffer(data, dtype, count=number, offset=at).astype(np.uint64), at

    for offsets_tag, counts_tag in ((273, 279), (324, 325)):  # strips, tiles
        offsets, _ = values(offsets_tag)
        counts, _ = values(counts_tag)
        if offsets is not None and counts is not None and len(offsets) == len(counts):
            if len(offsets) and int((offsets + counts).max()) > n:
                raise _damaged(path, "the TIFF image data run past the end of the file")
    found, at = values(274)
    if found is None or len(found) != 1:
        return 1, None
    value = int(found[0])
    return (value if 1 <= value <= 8 else 1), (at, order + _TIFF_TYPES[entries[274][0]])


def _exif_orientation(payload: bytes | None) -> int:
    """The Orientation (0x0112) of an EXIF block parsed by Pillow; 1 if absent or unreadable."""
    if not payload:
        return 1
    try:
        exif = Image.Exif()
        exif.load(payload)
        value = exif.get(0x0112)
    except Exception:  # noqa: BLE001 - any broken EXIF block means "no orientation"
        return 1
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


def _orient(arr: np.ndarray, orientation: int) -> np.ndarray:
    """A view of ``arr`` ``(H, W[, C])`` turned as Pillow's ``ImageOps.exif_transpose`` does."""
    if orientation == 2:  # FLIP_LEFT_RIGHT
        return arr[:, ::-1]
    if orientation == 3:  # ROTATE_180
        return arr[::-1, ::-1]
    if orientation == 4:  # FLIP_TOP_BOTTOM
        return arr[::-1]
    if orientation == 5:  # TRANSPOSE
        return arr.swapaxes(0, 1)
    if orientation == 6:  # ROTATE_270 (90 degrees clockwise)
        return np.rot90(arr, -1)
    if orientation == 7:  # TRANSVERSE
        return arr.swapaxes(0, 1)[::-1, ::-1]
    if orientation == 8:  # ROTATE_90 (90 degrees counter-clockwise)
        return np.rot90(arr)
    return arr


# What libjpeg says, on stderr, when it decodes damaged data: it goes on and returns a picture
# with gray filler or garbled blocks, so these make the file "truncated or corrupt". Its other
# warnings ("N extraneous bytes before marker", unknown JFIF revision, ...) are common in
# real files whose pixels are all there, and only logged.
_JPEG_DAMAGE = re.compile(
    r"Corrupt JPEG data: (?:premature end of data segment|bad Huffman code|"
    r"bad arithmetic code|found marker)|Premature end of JPEG file|"
    r"Inconsistent progression sequence"
)
_stderr_lock = threading.Lock()


@contextlib.contextmanager
def _decoder_messages() -> Iterator[list[str]]:
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


class _Decoded(NamedTuple):
    arr: np.ndarray  # (H, W[, C]) as stored in the file, before orientation
    orientation: int
    bgr: bool  # colour channels in OpenCV's BGR(A) order


def _read_array(path: Path) -> _Decoded:
    _check_file(path)
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise _fail(path, f"is not a readable .npy array ({exc})") from None
        if arr.dtype.kind not in "fiu":
            raise _fail(path, f"holds a {arr.dtype} array, expected numbers")
        return _Decoded(arr, 1, False)
    kind = _sniff(_read_head(path))
    if kind == "exr":
        arr, _ = _read_exr(path)
        return _Decoded(arr, 1, False)
    with _mapped(path) as data:
        orientation, patch = 1, None
        if kind == "jpeg":
            orientation = _exif_orientation(_check_jpeg(path, data))
        elif kind == "png":
            orientation = _exif_orientation(_check_png(path, data))
        elif kind == "webp":
            orientation = _exif_orientation(_check_webp(path, data))
        elif kind == "tiff":
            orientation, patch = _check_tiff(path, data)
        buf = np.frombuffer(data, np.uint8)
        if patch is not None and orientation != 1:
            # OpenCV's TIFF decoder applies (some) orientations itself, depending on its
            # version; decode a copy tagged "1" and apply the orientation here like for the
            # other formats.
            buf = buf.copy()
            at, dtype = patch
            buf[at : at + np.dtype(dtype).itemsize] = np.array([1], dtype).view(np.uint8)
        try:
            with _decoder_messages() as messages:
                arr = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        except cv2.error as exc:
            raise _fail(path, f"is not an image OpenCV can decode ({_one_line(exc)})") from None
        finally:
            del buf
    for message in messages:
        log.info("%s: the decoder says: %s", path, message)
    if kind == "jpeg" and arr is not None:
        damage = next((m for m in messages if _JPEG_DAMAGE.search(m)), None)
        if damage is not None:
            raise _damaged(path, f"libjpeg: {damage}")
    if arr is None:
        raise _fail(path, "is not an image OpenCV can decode (corrupt or unsupported format)")
    return _Decoded(arr, orientation, arr.ndim == 3 and arr.shape[2] >= 3)


def _planes(decoded: _Decoded) -> list[np.ndarray]:
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


def load_image(
    path: str | os.PathLike,
    linear: bool = False,
    alpha: Literal["mask", "error", "ignore"] = "mask",
    min_side: int = MIN_SIDE,
) -> LoadedImage:
    """Read an image file as upright linear RGB.

    Args:
        path: the file (PNG, JPEG, TIFF, BMP, WebP, OpenEXR, or ``.npy``).
        linear: the integer file holds linear values (do not decode sRGB).
        alpha: what an alpha channel means: ``"mask"`` (alpha > 0.5 is inside, the default),
            ``"error"`` (reject the file) or ``"ignore"``.
        min_side: smallest allowed height and width (the method's patches are 60 px).

    Returns:
        :class:`LoadedImage` with a ``(3, H, W)`` float32 linear image, turned upright by the
        file's EXIF orientation.

    Raises:
        ImageError: the file is missing, unreadable, empty, not an image, truncated or
            corrupt, zero-size, too small, has an unsupported channel count, or contains
            NaN/infinity.
    """
    path = Path(path)
    decoded = _read_array(path)
    arr, orientation = decoded.arr, decoded.orientation
    if arr.ndim not in (2, 3):
        raise _fail(path, f"has {arr.ndim} dimensions; expected a 2-D image (H, W[, C])")
    h, w = arr.shape[:2]
    if orientation >= 5:
        h, w = w, h
    c = arr.shape[2] if arr.ndim == 3 else 1
    if h == 0 or w == 0:
        raise _fail(path, "has zero size")
    if c not in (1, 2, 3, 4):
        raise _fail(path, f"has {c} channels; expected 1 (gray), 3 (RGB) or 4 (RGBA)")
    if arr.dtype == np.uint8:
        depth = 8
    elif arr.dtype == np.uint16:
        depth = 16
    elif arr.dtype.kind == "f":
        depth = 32
    else:
        raise _fail(path, f"has pixel type {arr.dtype}; expected uint8, uint16 or float")
    if depth == 32 and not np.isfinite(arr).all():
        raise _fail(path, f"contains {int((~np.isfinite(arr)).sum())} NaN or infinite values")
    if min(h, w) < min_side:
        raise _fail(path, f"is {w}x{h} px; at least {min_side} px per side is needed")
    planes = _planes(decoded)
    mask = None
    if c in (2, 4):
        if alpha == "error":
            raise _fail(path, "has an alpha channel; remove it or pass alpha='mask'")
        if alpha == "mask":
            # code > max // 2 is exactly code / max > 0.5 for 8 and 16 bits
            threshold = 0.5 if depth == 32 else (1 << depth) // 2 - 1
            inside = np.ascontiguousarray(_orient(planes[-1], orientation) > threshold)
            mask = torch.from_numpy(inside)[None]
            if not bool(mask.any()):
                raise _fail(path, "alpha channel is fully transparent (empty mask)")
        planes = planes[:-1]
    is_linear = linear or depth == 32
    out = np.empty((3, h, w), np.float32)
    for i, plane in enumerate(planes):
        plane = _orient(plane, orientation)
        if depth == 32:
            np.copyto(out[i], plane, casting="same_kind")
        elif depth == 8:
            cv2.LUT(np.ascontiguousarray(plane), decode_lut(8, is_linear), dst=out[i])
        else:
            np.take(decode_lut(16, is_linear), plane, out=out[i], mode="clip")
    if len(planes) == 1:  # gray: the same values in R, G and B
        out[1] = out[0]
        out[2] = out[0]
    if depth == 32 and float(out.min()) < 0:
        raise _fail(path, "has negative values; expected intensities >= 0")
    return LoadedImage(
        image=torch.from_numpy(out),
        mask=mask,
        path=path,
        bit_depth=depth,
        linear_file=is_linear,
        orientation=orientation,
    )


def load_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> torch.Tensor:
    """Read a mask file: nonzero (or alpha > 0.5 where present) is inside.

    Args:
        path: an image file; colour masks count a pixel as inside if any channel is nonzero.
            The EXIF orientation is applied as for :func:`load_image`.
        shape: expected ``(H, W)``; a mismatch raises :class:`ImageError`.

    Returns:
        ``(1, H, W)`` bool tensor.

    Raises:
        ImageError: the file cannot be read (see :func:`load_image`), its size differs from
            ``shape``, or no pixel is inside.
    """
    path = Path(path)
    decoded = _read_array(path)
    arr = decoded.arr
    if arr.ndim < 2:
        raise _fail(path, f"has {arr.ndim} dimensions; expected a 2-D image (H, W[, C])")
    if arr.ndim == 3 and arr.shape[2] in (2, 4):
        inside = arr[..., -1] > (np.iinfo(arr.dtype).max / 2 if arr.dtype.kind == "u" else 0.5)
    else:
        inside = (arr.reshape(arr.shape[0], arr.shape[1], -1) > 0).any(axis=2)
    inside = _orient(inside, decoded.orientation)
    if shape is not None and inside.shape != tuple(shape):
        raise _fail(
            path,
            f"mask is {inside.shape[1]}x{inside.shape[0]} px but the image is "
            f"{shape[1]}x{shape[0]} px",
        )
    if not inside.any():
        raise _fail(path, "mask is empty (no pixel inside)")
    return torch.from_numpy(np.ascontiguousarray(inside))[None]


# ---------------------------------------------------------------------------------------------
# OpenEXR

# Header attributes that describe the file's layout: not returned as metadata, not writable.
_EXR_LAYOUT = frozenset(
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
    _check_file(path)
    if not _read_head(path).startswith(_EXR_MAGIC):
        raise _fail(path, "is not an OpenEXR file")
    return _read_exr(path)


def _read_exr(path: Path) -> tuple[np.ndarray, dict[str, Any]]:
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            if not exr.parts:  # the binding skips a part whose pixels it cannot decode
                raise _damaged(path, "OpenEXR cannot decode its pixel data")
            header = dict(exr.header())
            channels = dict(exr.channels())
    except ImageError:
        raise
    except Exception as exc:  # noqa: BLE001 - the binding raises RuntimeError, ValueError, ...
        raise _fail(path, f"is not a readable OpenEXR file ({_one_line(exc)})") from None
    if header.get("type") in (OpenEXR.deepscanline, OpenEXR.deeptile):
        raise _fail(path, "is a deep OpenEXR file; expected a flat image")
    names = set(channels)
    if {"R", "G", "B"} <= names:
        wanted = ["R", "G", "B"]
    elif "Y" in names and not names & {"RY", "BY"}:
        wanted = ["Y"]
    else:
        raise _fail(path, f"has OpenEXR channels {sorted(names)}; expected Y or R, G, B")
    if "A" in names:
        wanted.append("A")
    planes = []
    for name in wanted:
        channel = channels[name]
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise _fail(path, f"has a subsampled OpenEXR channel {name}; expected full size")
        if channel.pixels.dtype.kind != "f":
            raise _fail(path, f"has {channel.pixels.dtype} OpenEXR channel {name}; expected float")
        planes.append(channel.pixels)
    if len(planes) == 1:
        arr = planes[0].astype(np.float32, copy=False)
    else:
        arr = np.stack(planes, axis=-1).astype(np.float32, copy=False)
    metadata = {}
    for key, value in header.items():
        if key in _EXR_LAYOUT:
            continue
        if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.size == 1:
            value = float(value.reshape(()))  # the binding's form of a double attribute
        metadata[key] = value
    return arr, metadata


def _exr_attributes(path: Path, metadata: Mapping[str, float | str]) -> dict[str, Any]:
    """Header attributes for ``metadata``: numbers as double attributes, strings as strings."""
    attributes: dict[str, Any] = {}
    for key, value in metadata.items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"{path}: metadata keys must be non-empty strings, got {key!r}")
        if key in _EXR_LAYOUT:
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


def _write_exr(tmp: str, path: Path, arr: np.ndarray, attributes: dict[str, Any]) -> None:
    import OpenEXR

    if arr.ndim == 2:
        channels = {"Y": np.ascontiguousarray(arr, np.float32)}
    else:
        channels = {name: np.ascontiguousarray(arr[..., i]) for i, name in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes)
    try:
        with OpenEXR.File(header, channels) as exr:
            exr.write(tmp)
    except OSError:
        raise
    except Exception as exc:  # noqa: BLE001 - the binding raises RuntimeError, ValueError, ...
        raise ImageError(f"{path}: OpenEXR cannot write the file ({_one_line(exc)})") from None


# ---------------------------------------------------------------------------------------------
# Writing


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
        attributes = _exr_attributes(path, metadata or {})
        _write_atomically(path, lambda tmp: _write_exr(tmp, path, arr, attributes))
        return path
    if encoding == "npy":
        _atomic_write(path, arr, npy=True)
        return path
    lin = np.clip(arr, 0, 1)
    if encoding in ("srgb8", "srgb16"):
        lin = (
            linear_to_srgb(torch.from_numpy(lin)).numpy()
            if lin.ndim == 2
            else linear_to_srgb(torch.from_numpy(lin).permute(2, 0, 1)).permute(1, 2, 0).numpy()
        )
    if encoding == "srgb8":
        payload = np.round(lin * 255).astype(np.uint8)
    elif encoding in ("srgb16", "linear16"):
        payload = np.round(lin * 65535).astype(np.uint16)
    else:
        raise ValueError(f"unknown encoding {encoding!r}; use srgb8, srgb16, linear16, npy or exr")
    if payload.ndim == 3:
        payload = np.ascontiguousarray(payload[..., ::-1])  # RGB -> BGR for OpenCV
    _atomic_write(path, payload)
    return path


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

    _write_atomically(path, write)
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


def _umask() -> int:
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
        _write_atomically(path, lambda tmp: _write_npy(tmp, payload))
    else:
        _write_atomically(path, lambda tmp: _write_encoded(tmp, path, payload))


def _write_atomically(path: Path, write: Callable[[str], None]) -> None:
    """Let ``write`` fill a temporary file in the target folder, then rename it over ``path``.

    The temporary file (created ``0o600``) gets the mode of a normally created file,
    ``0o666`` less the umask, before the rename.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
