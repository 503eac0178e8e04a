"""Region features of selective search: colour spaces and colour / texture histograms.

The similarity of two regions in :func:`torchiid.features.proposals.selective_search` compares
their L1-normalised histograms (Uijlings et al. 2013): 25 bins per channel of the colour space,
and 10 bins of half-wave rectified Gaussian derivatives (sigma = 1) in 8 orientations per
channel. :func:`atom_histograms` counts them once per atom; a region's histogram is the sum over
its atoms.
"""

from __future__ import annotations

from functools import cache

import numpy as np

__all__ = [
    "COLOUR_BINS",
    "TEXTURE_BINS",
    "ORIENTATIONS",
    "NUM_COLOUR_HIST_BINS",
    "to_colour_space",
    "gaussian_derivatives",
    "atom_histograms",
]

#: colour histogram bins per channel
COLOUR_BINS = 25
#: texture histogram bins per channel and orientation
TEXTURE_BINS = 10
#: orientations of the texture derivatives (every 45 degrees)
ORIENTATIONS = 8
#: the colour part of a histogram row (its first bins; the texture bins follow)
NUM_COLOUR_HIST_BINS = 3 * COLOUR_BINS


@cache
def _kernels():
    """The compiled histogram kernels, or ``None`` where the solvers' kernels are off too.

    That is: no numba, or ``TORCHIID_KERNELS=torch`` (:func:`torchiid.priors.kernels._numba`).
    """
    from torchiid.priors import kernels

    if kernels._numba() is None:
        return None
    try:
        from torchiid.features import histogram_kernels
    except Exception:  # pragma: no cover - e.g. no writable directory for numba's cache
        return None
    return histogram_kernels


def to_colour_space(srgb: np.ndarray, space: str) -> np.ndarray:
    """``HxWx3`` sRGB in ``[0, 1]`` to the colour space, every channel scaled to ``[0, 1]``.

    OpenCV's float conversions (D65 CIELab from sRGB; HSV with hue in degrees).
    """
    if space == "rgb":
        return srgb
    # OpenCV is imported on first use, not with the package: its 10 MB are then not resident
    # during Stage 0's CNN pass, one of a decomposition's two peaks of memory
    import cv2

    x = np.ascontiguousarray(srgb, dtype=np.float32)
    if space == "hsv":
        hsv = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)
        hsv[..., 0] /= 360.0
        return hsv.astype(np.float64)
    lab = cv2.cvtColor(x, cv2.COLOR_RGB2Lab).astype(np.float64)
    return np.stack(
        [lab[..., 0] / 100.0, (lab[..., 1] + 128.0) / 255.0, (lab[..., 2] + 128.0) / 255.0], -1
    ).clip(0.0, 1.0)


def gaussian_derivatives(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d/dx, d/dy)`` of a float32 ``HxW`` image with Gaussian derivative filters, sigma 1."""
    import cv2  # on first use (see to_colour_space)

    u = np.arange(-4, 5, dtype=np.float32)
    g = np.exp(-0.5 * u * u)
    g /= g.sum()
    dg = u * g  # cv2 correlates: the kernel of d/du (G * I) is G'(-u) = u g(u)
    gx = cv2.sepFilter2D(x, -1, dg, g, borderType=cv2.BORDER_REFLECT)
    gy = cv2.sepFilter2D(x, -1, g, dg, borderType=cv2.BORDER_REFLECT)
    return gx, gy


def atom_histograms(x: np.ndarray, atoms: np.ndarray, n_atoms: int) -> np.ndarray:
    """Colour and texture histogram counts of every atom, ``(A, 75 + 240)`` float64.

    Colour: 25 bins per channel of ``x`` (values in ``[0, 1]``). Texture: per channel and
    orientation ``o * 45`` degrees, the Gaussian derivative (sigma = 1) along that direction,
    half-wave rectified, scaled by the channel's largest response and cut into 10 bins (an
    orientation and its opposite share an axis: where one responds, the other is in bin 0).
    Computed one channel at a time, so memory stays ``O(H W)``; with numba, in one compiled
    pass per channel (:mod:`torchiid.features.histogram_kernels`, the same counts).
    """
    xf = np.ascontiguousarray(x, dtype=np.float32)
    n_bins = 3 * COLOUR_BINS + 3 * ORIENTATIONS * TEXTURE_BINS
    hist = np.zeros((n_atoms, n_bins))
    half = ORIENTATIONS // 2
    theta = np.arange(half) * (np.pi / half)
    kernel = _kernels()
    if kernel is not None:  # one pass per channel, the same counts (see histogram_kernels)
        atoms_c = np.ascontiguousarray(atoms, dtype=np.int64)
        kernel.colour_counts(xf, atoms_c, COLOUR_BINS, hist)
        cos32, sin32 = np.cos(theta).astype(np.float32), np.sin(theta).astype(np.float32)
        for c in range(3):
            gx, gy = gaussian_derivatives(np.ascontiguousarray(xf[..., c]))
            biggest = float(kernel.largest_response(gx, gy, cos32, sin32))
            scale = np.float32(TEXTURE_BINS / max(biggest, 1e-12))
            base = 3 * COLOUR_BINS + c * ORIENTATIONS * TEXTURE_BINS
            kernel.texture_counts(gx, gy, cos32, sin32, scale, atoms_c, base, TEXTURE_BINS, hist)
        return hist

    def add(base: int, q: np.ndarray, nb: int) -> None:
        counts = np.bincount(atoms * nb + q.reshape(-1), minlength=n_atoms * nb)
        hist[:, base : base + nb] += counts.reshape(n_atoms, nb)

    for c in range(3):
        q = np.minimum((xf[..., c] * COLOUR_BINS).astype(np.int64), COLOUR_BINS - 1)
        add(c * COLOUR_BINS, q, COLOUR_BINS)
    for c in range(3):
        gx, gy = gaussian_derivatives(np.ascontiguousarray(xf[..., c]))
        d = [np.float32(np.cos(t)) * gx + np.float32(np.sin(t)) * gy for t in theta]
        scale = TEXTURE_BINS / max(max(float(np.abs(di).max()) for di in d), 1e-12)
        for k, dk in enumerate(d):
            q = np.minimum((np.abs(dk) * scale).astype(np.int64), TEXTURE_BINS - 1)
            base = 3 * COLOUR_BINS + (c * ORIENTATIONS + k) * TEXTURE_BINS
            add(base, np.where(dk > 0, q, 0), TEXTURE_BINS)
            add(base + half * TEXTURE_BINS, np.where(dk < 0, q, 0), TEXTURE_BINS)
    return hist
