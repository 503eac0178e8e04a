"""Bands of rows: large images computed a part at a time.

Two reasons to work on a band of rows rather than on the whole image: memory (the
full-resolution passes of a 24-megapixel photo hold one band's temporaries at a time, not a
dozen full-size copies; bands of :data:`BAND_PIXELS`) and speed (a chain of per-pixel
operations reads back what the step before wrote from the CPU's caches instead of from
memory; bands of :data:`CACHE_PIXELS`, :func:`by_rows`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import torch

__all__ = ["BAND_PIXELS", "CACHE_PIXELS", "by_rows", "row_bands"]

#: pixels per band of the banded full-resolution passes (about 1 megapixel)
BAND_PIXELS = 1 << 20

#: pixels per band of :func:`by_rows`: 256 Ki, 3 MB for a float32 RGB temporary
CACHE_PIXELS = 1 << 18


def row_bands(height: int, width: int, pixels: int = BAND_PIXELS) -> Iterator[slice]:
    """Slices of rows covering ``height`` rows, each of about ``pixels`` pixels."""
    rows = max(1, pixels // max(width, 1))
    for y in range(0, height, rows):
        yield slice(y, min(height, y + rows))


def by_rows(fn: Callable[..., Any], *tensors: torch.Tensor) -> Any:
    """``fn(*tensors)`` for a per-pixel ``fn``, computed on bands of rows on the CPU.

    ``fn`` must compute each output pixel from the same pixel of its inputs (arithmetic,
    colour conversions; per-image values such as a quantile are computed before and taken
    from its closure), and return one tensor or a tuple of tensors of the inputs' height and
    width. On a 12-megapixel photo a chain of such operations otherwise writes a full-size
    temporary at every step and reads it back from memory, which takes several times as long
    as the arithmetic. The result is ``fn(*tensors)``'s: exactly, for arithmetic; to the last
    bit or two for functions such as ``pow`` and ``exp``, whose vectorised and scalar code
    paths round differently and which a band's end moves from one to the other (as a change
    of the thread count does for the whole image); where ``fn`` steps (CIELab's curve at its
    threshold), such a bit can move a value by the step. GPU tensors and images of up to two
    bands are passed to ``fn`` whole.

    Args:
        fn: the per-pixel function.
        *tensors: ``(..., H, W)`` tensors of one height and width (the leading dimensions may
            differ and broadcast in ``fn``).

    Returns:
        what ``fn`` returns.
    """
    h, w = tensors[0].shape[-2:]
    if any(t.shape[-2:] != (h, w) for t in tensors):
        raise ValueError(f"by_rows needs one height and width, got {[t.shape for t in tensors]}")
    if h * w <= 2 * CACHE_PIXELS or any(t.device.type != "cpu" for t in tensors):
        return fn(*tensors)
    single = True
    out: list[torch.Tensor] = []
    for rows in row_bands(h, w, CACHE_PIXELS):
        part = fn(*(t[..., rows, :] for t in tensors))
        single = isinstance(part, torch.Tensor)
        parts: tuple[torch.Tensor, ...] = (part,) if isinstance(part, torch.Tensor) else part
        if not out:
            for first in parts:
                out.append(first.new_empty((*first.shape[:-2], h, first.shape[-1])))
        for whole, band in zip(out, parts, strict=True):
            whole[..., rows, :] = band
    return out[0] if single else tuple(out)
