"""Felzenszwalb–Huttenlocher graph segmentation, one entry point for the whole package.

Selective search (:mod:`torchiid.features.proposals`) and the representative pixels of the global
reflectance term (:mod:`torchiid.priors.representatives`) both over-segment an image with the
graph-based method of Felzenszwalb & Huttenlocher (IJCV 2004): an 8-connected pixel graph with
Euclidean colour distances as edge weights, Gaussian pre-smoothing ``sigma``, merging threshold
``k / |component|`` and a minimum component size.

Two implementations compute it:

- ``"opencv"``: ``cv2.ximgproc.segmentation.createGraphSegmentation`` (C++), shipped by the
  ``opencv-contrib-python-headless`` wheel that torchiid depends on; 2.5–4× faster than
  scikit-image's at 512×384 (the pipeline's segments step: 0.11 s against 0.41 s);
- ``"skimage"``: :func:`skimage.segmentation.felzenszwalb`, used when the installed OpenCV lacks
  the contrib modules (for example when plain ``opencv-python`` was installed over the contrib
  wheel; a warning is logged once).

Both take ``k`` on the 0–255 value scale of the original paper (scikit-image divides its ``scale``
by 255 internally; OpenCV is given the values times 255). They implement the same algorithm but
differ in details (smoothing kernel, tie order), so labels are not identical; the segmentations
agree closely in size and number of segments.
"""

from __future__ import annotations

import logging
from functools import cache

import numpy as np

from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = ["graph_segmentation", "segmentation_backend"]

logger = logging.getLogger(__name__)


@cache
def segmentation_backend() -> str:
    """``"opencv"`` when ``cv2.ximgproc`` is importable, else ``"skimage"`` (logged once)."""
    try:
        import cv2

        cv2.ximgproc.segmentation.createGraphSegmentation  # noqa: B018
    except (ImportError, AttributeError):
        logger.warning(
            "cv2.ximgproc is missing (install opencv-contrib-python-headless); using the slower "
            "scikit-image Felzenszwalb segmentation"
        )
        return "skimage"
    return "opencv"


def graph_segmentation(
    image: np.ndarray,
    scale: float,
    sigma: float = 0.8,
    min_size: int = 20,
    backend: str | None = None,
) -> np.ndarray:
    """Felzenszwalb–Huttenlocher segmentation of an ``HxWxC`` image with values in ``[0, 1]``.

    Args:
        image: float array ``(H, W, C)``, channels scaled to ``[0, 1]`` (sRGB, HSV, scaled Lab).
        scale: the threshold ``k`` on the 0–255 scale (larger: larger segments).
        sigma: Gaussian pre-smoothing width in pixels.
        min_size: components smaller than this are merged into a neighbour.
        backend: ``"opencv"`` or ``"skimage"``; default :func:`segmentation_backend`.

    Returns:
        ``(H, W)`` int64 labels ``0 .. n-1``.

    Example:
        >>> img = np.zeros((20, 30, 3))
        >>> img[:, 15:] = 1.0
        >>> labels = graph_segmentation(img, scale=100, min_size=50)
        >>> int(labels.max()) + 1, bool(labels[0, 0] != labels[0, -1])
        (2, True)
    """
    if not isinstance(image, np.ndarray) or image.ndim != 3:
        got = getattr(image, "shape", type(image).__name__)
        raise ShapeError(f"expected an HxWxC numpy array, got {got}")
    if not scale > 0 or not sigma > 0 or int(min_size) < 1:
        raise ParameterError(
            f"need scale > 0, sigma > 0, min_size >= 1; got {scale}, {sigma}, {min_size}"
        )
    backend = segmentation_backend() if backend is None else backend
    if backend == "opencv":
        import cv2

        seg = cv2.ximgproc.segmentation.createGraphSegmentation(
            sigma=float(sigma), k=float(scale), min_size=int(min_size)
        )
        labels = seg.processImage(np.ascontiguousarray(image * 255.0, dtype=np.float32))
    elif backend == "skimage":
        from skimage.segmentation import felzenszwalb

        labels = felzenszwalb(
            np.ascontiguousarray(image, dtype=np.float64),
            scale=float(scale),
            sigma=float(sigma),
            min_size=int(min_size),
            channel_axis=-1,
        )
    else:
        raise ParameterError(f"backend must be 'opencv' or 'skimage', got {backend!r}")
    return _compact(labels.astype(np.int64))


def _compact(labels: np.ndarray) -> np.ndarray:
    """Relabel to ``0 .. n-1``, keeping the order of the old labels."""
    _, inverse = np.unique(labels, return_inverse=True)
    return inverse.reshape(labels.shape).astype(np.int64)
