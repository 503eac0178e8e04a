"""The numba kernel behind :func:`torchiid.features.proposal_features.atom_histograms`.

Imported only when numba is (and ``TORCHIID_KERNELS`` is not ``torch``). One pass over the
pixels adds every pixel to its atom's colour and texture bins, where the numpy path makes 27
``bincount`` calls and as many quantised copies of the image; the arithmetic is the numpy
path's, in float32 and in its order, so the counts are the same.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["colour_counts", "largest_response", "texture_counts"]


def _colour_counts(xf, atoms, bins, hist):  # pragma: no cover - compiled
    """``hist[a, c·bins + q] += 1``, ``q = min(⌊x_c · bins⌋, bins − 1)`` (float32 product)."""
    h, w, nc = xf.shape
    nb = np.float32(bins)
    for i in range(h):
        for j in range(w):
            a = atoms[i * w + j]
            for c in range(nc):
                q = min(np.int64(xf[i, j, c] * nb), bins - 1)
                hist[a, c * bins + q] += 1.0
    return hist


def _largest_response(gx, gy, cos32, sin32):  # pragma: no cover - compiled
    """``max_k max |cos_k · gx + sin_k · gy|`` (float32 products and sum)."""
    h, w = gx.shape
    m = np.float32(0.0)
    for k in range(cos32.shape[0]):
        ck = cos32[k]
        sk = sin32[k]
        for i in range(h):
            for j in range(w):
                d = ck * gx[i, j] + sk * gy[i, j]
                m = max(m, abs(d))
    return m


def _texture_counts(gx, gy, cos32, sin32, scale, atoms, base, bins, hist):  # pragma: no cover
    """Count each axis ``k``'s rectified responses of the pixels into their atoms' rows.

    The positive side's bin lies at ``base + k·bins``, the negative side's at ``base + (K +
    k)·bins`` (bin 0 where that side does not respond); ``q = min(⌊|d| · scale⌋, bins − 1)``
    with ``scale`` a float32.
    """
    h, w = gx.shape
    nk = cos32.shape[0]
    for i in range(h):
        for j in range(w):
            a = atoms[i * w + j]
            for k in range(nk):
                d = cos32[k] * gx[i, j] + sin32[k] * gy[i, j]
                q = min(np.int64(abs(d) * scale), bins - 1)
                hist[a, base + k * bins + (q if d > 0 else 0)] += 1.0
                hist[a, base + (nk + k) * bins + (q if d < 0 else 0)] += 1.0
    return hist


# IEEE semantics: the bins must be the numpy path's, so no fused or reordered arithmetic
colour_counts = njit(nogil=True, cache=True, boundscheck=False)(_colour_counts)
largest_response = njit(nogil=True, cache=True, boundscheck=False)(_largest_response)
texture_counts = njit(nogil=True, cache=True, boundscheck=False)(_texture_counts)
