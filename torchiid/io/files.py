"""Reading an image file's bytes, and the one-line errors of the image readers.

Every problem with an input file is an :class:`~torchiid.core.exceptions.ImageError` whose
message names the file and the problem on one line (:func:`fail`, :func:`damaged`); the
readers check that the file exists, is a readable, non-empty file (:func:`check_file`), tell
its format from its first bytes (:func:`sniff`) and read it memory-mapped (:func:`file_bytes`).
"""

from __future__ import annotations

import contextlib
import mmap
import os
from collections.abc import Iterator
from pathlib import Path

from torchiid.core.exceptions import ImageError

__all__ = [
    "EXR_MAGIC",
    "PNG_SIGNATURE",
    "check_file",
    "damaged",
    "fail",
    "file_bytes",
    "one_line",
    "read_head",
    "sniff",
]


def fail(path: Path, problem: str) -> ImageError:
    """The error for ``path`` with ``problem``: ``"<path>: <problem>"``."""
    return ImageError(f"{path}: {problem}")


def damaged(path: Path, detail: str) -> ImageError:
    """The error for a file whose data end early or break their format."""
    return fail(path, f"is truncated or corrupt ({detail})")


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (its type name when it has none)."""
    return " ".join(str(exc).split()) or type(exc).__name__


def check_file(path: Path) -> None:
    """Raise :class:`ImageError` unless ``path`` is a readable, non-empty file."""
    if not path.exists():
        raise fail(path, "no such file")
    if path.is_dir():
        raise fail(path, "is a directory, not an image file")
    if not os.access(path, os.R_OK):
        raise fail(path, "cannot be read (permission denied)")
    if path.stat().st_size == 0:
        raise fail(path, "is empty (0 bytes)")


def read_head(path: Path, n: int = 16) -> bytes:
    """The first ``n`` bytes of the file."""
    try:
        with open(path, "rb") as fh:
            return fh.read(n)
    except OSError as exc:
        raise fail(path, f"cannot be read ({one_line(exc)})") from None


@contextlib.contextmanager
def file_bytes(path: Path) -> Iterator[mmap.mmap | bytes]:
    """The file's bytes, memory-mapped read-only where possible (no copy in memory)."""
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise fail(path, f"cannot be read ({one_line(exc)})") from None
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


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXR_MAGIC = b"\x76\x2f\x31\x01"


def sniff(head: bytes) -> str:
    """The format of a file from its first bytes: ``"jpeg"``, ``"png"``, ..., or ``"other"``."""
    if head.startswith(b"\xff\xd8"):
        return "jpeg"
    if head.startswith(PNG_SIGNATURE):
        return "png"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "webp"
    if head.startswith(EXR_MAGIC):
        return "exr"
    return "other"
