"""Reading a folder of decompositions (the layers ``torchiid decompose`` writes) for scoring."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from torchiid.core.exceptions import ParameterError, ShapeError, TorchiidError
from torchiid.io import linear_to_srgb, load_image, srgb_to_linear

__all__ = [
    "LAYERS",
    "check_results_folder",
    "input_decoding",
    "layer_file",
    "layer_names",
    "load_layer",
    "read_layer",
]

LAYERS = ("reflectance", "shading")

#: the relative residual (after the best scale) under which the layers' product is taken to
#: be an input, and the one above which it is taken not to be (see :func:`input_decoding`)
_MATCH, _MISMATCH = 0.05, 0.1


def layer_names(sample_id: str, layer: str) -> list[tuple[str, bool]]:
    """The file names :func:`load_layer` looks for, in order, each with "holds linear values".

    ``<id>-<layer>.npy``, then ``<id>-reflectance-linear16.png`` / ``<id>-shading.exr``, then
    ``<id>-<layer>.png`` (8-bit sRGB).

    Raises:
        ParameterError: ``layer`` is neither ``"reflectance"`` nor ``"shading"``.
    """
    if layer not in LAYERS:
        raise ParameterError(f"expected layer 'reflectance' or 'shading', got {layer!r}")
    exact = "reflectance-linear16.png" if layer == "reflectance" else "shading.exr"
    return [
        (f"{sample_id}-{layer}.npy", False),
        (f"{sample_id}-{exact}", True),
        (f"{sample_id}-{layer}.png", False),
    ]


def layer_file(results: str | Path, sample_id: str, layer: str) -> tuple[Path, bool]:
    """The file :func:`load_layer` reads: the first of :func:`layer_names` that exists.

    Returns:
        ``(path, linear)``: the file, and whether its integer values are linear (the 16-bit
        PNG) rather than sRGB.

    Raises:
        ParameterError: ``layer`` is neither ``"reflectance"`` nor ``"shading"``.
        TorchiidError: none of the three files exists.
    """
    results = Path(results)
    candidates = layer_names(sample_id, layer)
    for name, linear in candidates:
        if (results / name).is_file():
            return results / name, linear
    raise TorchiidError(f"{results}: none of {', '.join(n for n, _ in candidates)}")


def read_layer(path: str | Path, layer: str, *, linear: bool = False) -> torch.Tensor:
    """One layer file as ``(1, C, H, W)`` linear (see :func:`load_layer`).

    Args:
        path: the file.
        layer: ``"reflectance"`` or ``"shading"`` (the shading is the mean of the channels).
        linear: integer values are linear (else sRGB, decoded); float files are linear.

    Raises:
        ImageError: the file cannot be read, or an ``.npy`` array is not ``(H, W)`` or
            ``(H, W, C)`` (:func:`~torchiid.io.validate.check_pixels`).
    """
    path = Path(path)
    img = load_image(path, linear=linear, alpha="ignore", min_side=1).image
    return (img.mean(dim=0, keepdim=True) if layer == "shading" else img)[None]


def load_layer(
    results: str | Path, sample_id: str, layer: str, size: tuple[int, int] | None = None
) -> torch.Tensor:
    """One layer of a results folder as ``(1, C, H, W)`` linear.

    The exact files are preferred: ``<id>-<layer>.npy`` (float32 linear, ``(H, W)`` or
    ``(H, W, 3)``, ``torchiid decompose --save-npy``), then ``<id>-reflectance-linear16.png``
    (16-bit linear) / ``<id>-shading.exr`` (float OpenEXR), and only then the viewable 8-bit
    sRGB ``<id>-<layer>.png`` (decoded to linear). The first file that exists is read (with
    :func:`torchiid.io.load_image`, any size, alpha ignored); the shading is the mean of the
    file's channels.

    Args:
        results: the results folder.
        sample_id: the image's id (file names start with ``<id>-``).
        layer: ``"reflectance"`` or ``"shading"``.
        size: the image's ``(H, W)``, which the layer must have (``None``: any).

    Returns:
        ``(1, 3, H, W)`` reflectance or ``(1, 1, H, W)`` shading, float32, linear.

    Raises:
        ParameterError: ``layer`` is neither ``"reflectance"`` nor ``"shading"``.
        TorchiidError: none of the three files exists.
        ImageError: the file found cannot be read, or is an ``.npy`` array of another shape
            (e.g. channels first).
        ShapeError: the layer is not of ``size``; the message names the file.
    """
    path, linear = layer_file(results, sample_id, layer)
    x = read_layer(path, layer, linear=linear)
    if size is not None and tuple(x.shape[-2:]) != tuple(size):
        raise ShapeError(f"{layer} {path} is {tuple(x.shape[-2:])} but the image is {size}")
    return x


def check_results_folder(results: str | Path, ids: Sequence[str], what: str = "id") -> None:
    """Refuse a results folder that holds no layer file of any of ``ids``.

    One missing image is that image's failure; a folder without any is a set-up error
    (another folder, or files named otherwise), found before any work.

    Args:
        results: the results folder.
        ids: the ids of the run.
        what: what an id is, for the message (``"MIT object name"``).

    Raises:
        TorchiidError: the folder holds none of the files :func:`load_layer` looks for, for
            any of ``ids``; the message names the folder, the files and some of the layer
            files it holds under other names.
    """
    results = Path(results)
    if not ids:
        return
    for i in ids:
        for layer in LAYERS:
            if any((results / name).is_file() for name, _ in layer_names(i, layer)):
                return
    others = sorted(
        p.name
        for p in results.iterdir()
        if p.is_file() and any(f"-{layer}" in p.name for layer in LAYERS)
    )
    held = (
        f"; it holds {', '.join(others[:3])}{' ...' if len(others) > 3 else ''}"
        if others
        else "; it holds no layer files"
    )
    pairs = zip(*(layer_names("<id>", layer) for layer in LAYERS), strict=True)
    looked = ", else ".join(" and ".join(name for name, _ in pair) for pair in pairs)
    raise TorchiidError(
        f"{results}: no layers of any of the {len(ids)} image(s) to score: looked for {looked}, "
        f"with <id> the {what} (e.g. {ids[0]}-reflectance.npy){held}"
    )


def _residual(product: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    """``min_a ‖a·product − target‖ / ‖target‖`` over the masked pixels (``inf`` if empty)."""
    m = mask.expand_as(target)
    p, t = product.expand_as(target)[m].double(), target[m].double()
    pp, tt = float((p * p).sum()), float(t.norm())
    if pp == 0 or tt == 0:
        return float("inf")
    a = float((p * t).sum()) / pp
    return float((a * p - t).norm()) / tt


def input_decoding(
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> str | None:
    """Whether a decomposition was made from the input decoded in the wrong colour encoding.

    A decomposition whose layers multiply to its input (``R · S = I``, as ``torchiid
    decompose`` writes them) tells which values it was made from. Only when ``R · S`` (up
    to a global scale, over the masked pixels) lies more than 10 % from the dataset's linear
    image and within 5 % of that image decoded the other way does this name that decoding;
    a method whose layers multiply to neither (or to both: an image whose values barely
    vary) gives ``None``. The exact files of ``decompose`` multiply to their input to about
    1e-5, its 8-bit PNGs (rounded, clipped) to about 3 % and up to 10 %, so layers read from
    8-bit PNGs alone may go unnamed.

    Args:
        image: the dataset's linear input, ``(3, H, W)`` or ``(1, 3, H, W)``.
        reflectance: ``(1, 3, H, W)`` (or ``(3, H, W)``) linear.
        shading: ``(1, 1 or 3, H, W)`` (or unbatched) linear.
        mask: the pixels to compare (``(1, H, W)``, ``(1, 1, H, W)`` or ``None`` for all).

    Returns:
        ``"srgb"``: the layers are those of the linear input taken as sRGB and decoded
        (a 16-bit linear file decomposed without ``--linear``); ``"linear"``: those of the
        sRGB-encoded input taken as linear (an sRGB photo decomposed with ``--linear``);
        ``None`` otherwise.
    """
    image = image.reshape(-1, *image.shape[-2:]).float()
    product = (
        reflectance.reshape(-1, *reflectance.shape[-2:]) * shading.reshape(-1, *shading.shape[-2:])
    ).float()
    h, w = image.shape[-2:]
    if tuple(product.shape[-2:]) != (h, w):
        return None
    m = torch.ones(1, h, w, dtype=torch.bool) if mask is None else mask.reshape(1, h, w) != 0
    if product.shape[0] not in (1, 3) or not bool(m.any()):
        return None
    right = _residual(product, image, m)
    if right <= _MISMATCH:
        return None
    for name, other in (("srgb", srgb_to_linear(image)), ("linear", linear_to_srgb(image))):
        if _residual(product, other, m) <= _MATCH:
            return name
    return None
