"""Turning the files and folders a user names into the list of images to process."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from torchiid.core.exceptions import TorchiidError

__all__ = ["IMAGE_SUFFIXES", "collect_inputs"]

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr", ".npy"}
"""File suffixes (lower case) taken from a folder by :func:`collect_inputs`."""


def collect_inputs(inputs: Sequence[Path]) -> list[Path]:
    """Expand directories into their image files (sorted); keep files as given.

    Args:
        inputs: Files and/or directories. A directory contributes its files (not recursively)
            whose suffix, in lower case, is one of :data:`IMAGE_SUFFIXES`.

    Returns:
        The image paths, in the order given, each directory's files sorted.

    Raises:
        TorchiidError: A directory holds no image file.
    """
    out: list[Path] = []
    for p in inputs:
        if p.is_dir():
            found = sorted(
                q for q in p.iterdir() if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES
            )
            if not found:
                raise TorchiidError(
                    f"{p}: directory holds no image files ({', '.join(sorted(IMAGE_SUFFIXES))})"
                )
            out.extend(found)
        else:
            out.append(p)
    return out
