"""Reading a folder of decompositions (the layers ``torchiid decompose`` writes) for scoring."""

from __future__ import annotations

from pathlib import Path

import torch

from torchiid.core.exceptions import ParameterError, TorchiidError
from torchiid.io import load_image

__all__ = ["LAYERS", "load_layer"]

LAYERS = ("reflectance", "shading")


def load_layer(results: str | Path, sample_id: str, layer: str) -> torch.Tensor:
    """One layer of a results folder as ``(1, C, H, W)`` linear.

    The exact files are preferred: ``<id>-<layer>.npy`` (float32 linear,
    ``torchiid decompose --save-npy``), then ``<id>-reflectance-linear16.png`` (16-bit linear) /
    ``<id>-shading.exr`` (float OpenEXR), and only then the viewable 8-bit sRGB
    ``<id>-<layer>.png`` (decoded to linear). The first file that exists is read (with
    :func:`torchiid.io.load_image`, any size, alpha ignored); the shading is the mean of the
    file's channels.

    Args:
        results: the results folder.
        sample_id: the image's id (file names start with ``<id>-``).
        layer: ``"reflectance"`` or ``"shading"``.

    Returns:
        ``(1, 3, H, W)`` reflectance or ``(1, 1, H, W)`` shading, float32, linear.

    Raises:
        ParameterError: ``layer`` is neither ``"reflectance"`` nor ``"shading"``.
        TorchiidError: none of the three files exists.
        ImageError: the file found cannot be read.
    """
    if layer not in LAYERS:
        raise ParameterError(f"expected layer 'reflectance' or 'shading', got {layer!r}")
    results = Path(results)
    exact = "reflectance-linear16.png" if layer == "reflectance" else "shading.exr"
    candidates = [
        (results / f"{sample_id}-{layer}.npy", False),
        (results / f"{sample_id}-{exact}", True),
        (results / f"{sample_id}-{layer}.png", False),
    ]
    for path, linear in candidates:
        if path.is_file():
            img = load_image(path, linear=linear, alpha="ignore", min_side=1).image
            return (img.mean(dim=0, keepdim=True) if layer == "shading" else img)[None]
    names = ", ".join(p.name for p, _ in candidates)
    raise TorchiidError(f"{results}: none of {names}")
