"""Felzenszwalb–Huttenlocher graph segmentation, one entry point for the whole package.

Selective search (:mod:`torchiid.features.proposals`) and the representative pixels of the global
reflectance term (:mod:`torchiid.priors.representatives`, whose segments come from
:func:`felzenszwalb_segments` here) both over-segment an image with the graph-based method of
Felzenszwalb & Huttenlocher (IJCV 2004): an 8-connected pixel graph with Euclidean colour
distances as edge weights, Gaussian pre-smoothing ``sigma``, merging threshold ``k / |component|``
and a minimum component size.

Two implementations compute it:

- ``"opencv"``: ``cv2.ximgproc.segmentation.createGraphSegmentation`` (C++), shipped by the
  ``opencv-contrib-python-headless`` wheel that torchiid depends on, and several times faster
  than scikit-image's (the figures are on the documentation's Method page);
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
from collections.abc import Callable
from concurrent.futures import Executor
from functools import cache

import numpy as np
import torch

from torchiid.core.check import check_image
from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = [
    "graph_segmentation",
    "segmentation_backend",
    "felzenszwalb_segments",
    "start_felzenszwalb_segments",
]

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


def felzenszwalb_segments(
    image: torch.Tensor,
    *,
    linear: bool = True,
    scale: float = 200.0,
    sigma: float = 0.8,
    min_size: int = 100,
) -> torch.Tensor:
    """Felzenszwalb–Huttenlocher superpixels per image (:func:`graph_segmentation`).

    Runs on the sRGB encoding of the image in ``[0, 1]`` (``linear=True`` clamps a linear input
    to ``[0, 1]`` and encodes it with :func:`torchiid.core.colour.linear_to_srgb`). Defaults give
    about 150–300 segments on a 512×384 photo, so the global reflectance term ``C`` has a few
    ten thousand pairs.

    Args:
        image: RGB image in ``[0, 1]``, linear (default) or sRGB.
        linear: whether ``image`` is linear RGB.
        scale: larger values give larger segments.
        sigma: Gaussian pre-smoothing width in pixels.
        min_size: smallest segment in pixels (smaller ones are merged).

    Returns:
        Labels from 0 per image, on the image's device.

    Shape:
        ``(B, 3, H, W) -> (B, H, W)`` long.
    """
    return start_felzenszwalb_segments(
        image, linear=linear, scale=scale, sigma=sigma, min_size=min_size
    )()


def start_felzenszwalb_segments(
    image: torch.Tensor,
    *,
    linear: bool = True,
    scale: float = 200.0,
    sigma: float = 0.8,
    min_size: int = 100,
    executor: Executor | None = None,
) -> Callable[[], torch.Tensor]:
    """:func:`felzenszwalb_segments` that can run in the background.

    The torch part (sRGB encoding) runs now, in the calling thread; the segmentation itself
    (OpenCV's C++, which releases the GIL) is submitted to ``executor`` when given, so it
    overlaps whatever the caller does next. Call the returned function for the labels.

    Args:
        image: as for :func:`felzenszwalb_segments`.
        linear: as for :func:`felzenszwalb_segments`.
        scale: as for :func:`felzenszwalb_segments`.
        sigma: as for :func:`felzenszwalb_segments`.
        min_size: as for :func:`felzenszwalb_segments`.
        executor: where the segmentation runs; ``None``: in the caller of the returned function.

    Returns:
        A function without arguments returning the ``(B, H, W)`` long labels.
    """
    check_image(image, "image")
    srgb = linear_to_srgb(image) if linear else image.clamp(0.0, 1.0)
    arr = srgb.detach().to("cpu", torch.float32).permute(0, 2, 3, 1).numpy()
    device = image.device

    def run() -> list[np.ndarray]:
        return [graph_segmentation(a, scale=scale, sigma=sigma, min_size=min_size) for a in arr]

    future = executor.submit(run) if executor is not None else None

    def result() -> torch.Tensor:
        out = future.result() if future is not None else run()
        return torch.from_numpy(np.stack(out).astype(np.int64)).to(device)

    return result
