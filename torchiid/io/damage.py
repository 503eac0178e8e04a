"""Damage checks: a file whose data end early or break their format is rejected, never filled.

Before a file is decoded, its structure is walked (:func:`check_structure`):

* a JPEG's marker structure must be complete up to the end-of-image marker of its main image
  (bytes after it, such as the video of a motion photo, MPF / gain-map images or padding, are
  allowed);
* every PNG chunk must lie inside the file, critical chunks must match their CRC-32, and the
  IEND chunk must be there;
* WebP RIFF chunks, and the TIFF strips or tiles of the first image, must lie inside the file.

While a JPEG decodes, libjpeg's reports of damaged data (:data:`JPEG_DAMAGE`: premature end of
a data segment, bad Huffman code, ...), which it would otherwise paper over with gray filler or
garbled blocks, reject the file too. A JPEG has no checksum, so altered bytes inside its
compressed data that still decode cleanly cannot be detected.

The walks also find the EXIF block (JPEG APP1, PNG eXIf, WebP EXIF) or the TIFF Orientation
tag, so the file is read once for both.
"""

from __future__ import annotations

import mmap
import re
import struct
import zlib
from pathlib import Path

import numpy as np

from torchiid.io.files import PNG_SIGNATURE, damaged
from torchiid.io.orientation import exif_orientation

__all__ = [
    "JPEG_DAMAGE",
    "check_jpeg",
    "check_png",
    "check_structure",
    "check_tiff",
    "check_webp",
]

# What libjpeg says, on stderr, when it decodes damaged data: it goes on and returns a picture
# with gray filler or garbled blocks, so these make the file "truncated or corrupt". Its other
# warnings ("N extraneous bytes before marker", unknown JFIF revision, ...) are common in
# real files whose pixels are all there, and only logged.
JPEG_DAMAGE = re.compile(
    r"Corrupt JPEG data: (?:premature end of data segment|bad Huffman code|"
    r"bad arithmetic code|found marker)|Premature end of JPEG file|"
    r"Inconsistent progression sequence"
)


def check_structure(
    path: Path, kind: str, data: mmap.mmap | bytes
) -> tuple[int, tuple[int, str] | None]:
    """Check the structure of a file of format ``kind`` (:func:`~torchiid.io.files.sniff`).

    Returns:
        The EXIF Orientation (1 when absent) and, for a TIFF with the tag, the byte offset and
        numpy dtype of its value (:func:`check_tiff`).

    Raises:
        ImageError: the file is truncated or corrupt.
    """
    if kind == "tiff":
        return check_tiff(path, data)
    check = {"jpeg": check_jpeg, "png": check_png, "webp": check_webp}.get(kind)
    return (exif_orientation(check(path, data)) if check is not None else 1), None


# Where the entropy-coded data of a JPEG scan ends: 0xFF followed by a byte that is not a stuffed
# zero, a restart marker (RST0-7) or another fill 0xFF.
_JPEG_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def check_jpeg(path: Path, data: mmap.mmap | bytes) -> bytes | None:
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
            raise damaged(path, "the file ends before its JPEG end-of-image marker")
        while pos < n and data[pos] == 0xFF:
            pos += 1
        if pos >= n:
            raise damaged(path, "the file ends before its JPEG end-of-image marker")
        marker = data[pos]
        pos += 1
        if marker == 0xD9:
            if not scan:
                raise damaged(path, "JPEG end-of-image marker before any image data")
            return exif
        if marker == 0xD8:
            raise damaged(path, f"second JPEG start-of-image marker at byte {pos - 2}")
        if marker == 0x00 or marker == 0x01 or 0xD0 <= marker <= 0xD7:
            continue  # stuffed byte in garbage, TEM or a stray RSTn: no length field
        if pos + 2 > n:
            raise damaged(path, "the file ends inside a JPEG marker segment")
        end = pos + ((data[pos] << 8) | data[pos + 1])
        if end < pos + 2:
            raise damaged(path, f"JPEG marker segment of length < 2 at byte {pos - 2}")
        if end > n:
            raise damaged(path, "the file ends inside a JPEG marker segment")
        if marker == 0xE1 and exif is None and data[pos + 2 : pos + 8] == b"Exif\x00\x00":
            exif = bytes(data[pos + 2 : end])
        frame = frame or marker in _JPEG_SOF
        pos = end
        if marker == 0xDA:  # start of scan: skip its entropy-coded data
            if not frame:
                raise damaged(path, "JPEG scan before any frame header")
            scan = True
            found = _JPEG_SCAN_END.search(data, pos)
            if found is None:
                raise damaged(path, "the file ends inside the JPEG image data")
            pos = found.start()


def check_png(path: Path, data: mmap.mmap | bytes) -> bytes | None:
    """Walk the chunks of a PNG up to IEND, checking the CRC-32s; return the eXIf payload.

    An ancillary chunk with a wrong CRC is ignored, as libpng does; a critical one (IHDR,
    PLTE, IDAT, IEND) makes the file corrupt.

    Raises:
        ImageError: a chunk runs past the end of the file, a critical chunk's CRC is wrong, or
            IEND is missing.
    """
    n = len(data)
    pos, exif = len(PNG_SIGNATURE), None
    with memoryview(data) as view:
        while True:
            if pos + 12 > n:
                raise damaged(path, "the file ends before the PNG IEND chunk")
            length = int.from_bytes(view[pos : pos + 4], "big")
            kind = bytes(view[pos + 4 : pos + 8])
            name = kind.decode("latin-1") if kind.isalpha() else f"0x{kind.hex()}"
            end = pos + 12 + length
            if length > 0x7FFFFFFF:
                raise damaged(path, f"PNG chunk length {length} at byte {pos}")
            if end > n:
                raise damaged(path, f"the file ends inside the PNG {name} chunk")
            if pos == len(PNG_SIGNATURE) and kind != b"IHDR":
                raise damaged(path, f"the first PNG chunk is {name}, not IHDR")
            critical = not (kind[0] & 0x20)
            if critical or (kind == b"eXIf" and exif is None):
                crc_ok = zlib.crc32(view[pos + 4 : end - 4]) == int.from_bytes(
                    view[end - 4 : end], "big"
                )
                if critical and not crc_ok:
                    raise damaged(path, f"CRC mismatch in the PNG {name} chunk at byte {pos}")
                if kind == b"eXIf" and crc_ok:
                    exif = bytes(view[pos + 8 : end - 4])
            if kind == b"IEND":
                return exif
            pos = end


def check_webp(path: Path, data: mmap.mmap | bytes) -> bytes | None:
    """Check that the RIFF chunks of a WebP file lie inside it; return the EXIF payload."""
    n = len(data)
    riff_end = 8 + int.from_bytes(data[4:8], "little")
    if riff_end > n:
        raise damaged(path, f"the WebP data should be {riff_end} bytes, the file has {n}")
    pos, exif = 12, None
    while pos + 8 <= riff_end:
        size = int.from_bytes(data[pos + 4 : pos + 8], "little")
        end = pos + 8 + size
        if end > riff_end:
            raise damaged(path, f"the WebP chunk at byte {pos} runs past the end of the data")
        if data[pos : pos + 4] == b"EXIF" and exif is None:
            exif = bytes(data[pos + 8 : end])
        pos = end + (size & 1)
    return exif


_TIFF_TYPES = {1: "u1", 3: "u2", 4: "u4", 16: "u8"}  # BYTE, SHORT, LONG, LONG8


def check_tiff(path: Path, data: mmap.mmap | bytes) -> tuple[int, tuple[int, str] | None]:
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
        raise damaged(path, "the TIFF image directory lies past the end of the file") from None

    def values(tag: int) -> tuple[np.ndarray | None, int]:
        if tag not in entries or entries[tag][0] not in _TIFF_TYPES:
            return None, 0
        kind, number, at = entries[tag]
        dtype = np.dtype(order + _TIFF_TYPES[kind])
        if number * dtype.itemsize > field:  # the field holds an offset to the values
            (at,) = struct.unpack_from(order + ("Q" if big else "I"), data, at)
        if at + number * dtype.itemsize > n:
            raise damaged(path, f"the values of TIFF tag {tag} lie past the end of the file")
        return np.frombuffer(data, dtype, count=number, offset=at).astype(np.uint64), at

    for offsets_tag, counts_tag in ((273, 279), (324, 325)):  # strips, tiles
        offsets, _ = values(offsets_tag)
        counts, _ = values(counts_tag)
        if offsets is not None and counts is not None and len(offsets) == len(counts):
            if len(offsets) and int((offsets + counts).max()) > n:
                raise damaged(path, "the TIFF image data run past the end of the file")
    found, at = values(274)
    if found is None or len(found) != 1:
        return 1, None
    value = int(found[0])
    return (value if 1 <= value <= 8 else 1), (at, order + _TIFF_TYPES[entries[274][0]])
