"""Writing a decomposition to files: what ``torchiid decompose`` leaves in its output folder.

For an input ``photo.jpg`` (``stem = "photo"``):

========================================  ====================================================
file                                      what it is
========================================  ====================================================
``photo-reflectance.png``                 reflectance ``R``, 8-bit **sRGB**; ``R`` is an albedo
                                          in [0, 1], so nothing is clipped
``photo-shading.png``                     shading ``S / shading_white``, 8-bit **sRGB** gray;
                                          ``shading_white`` (the shading's 99th percentile,
                                          recorded in ``photo-info.json``) shows as white,
                                          the brightest 1% clip
``photo-preview.png``                     ``[I | R | S / shading_white]`` side by side, sRGB,
                                          each panel at most 1024 px on its longer side
``photo-reflectance-linear16.png``        ``R``, 16-bit **linear** PNG, unclipped
``photo-shading.exr``                     ``S``, 32-bit float **linear** OpenEXR (one channel
                                          ``Y``), unclipped, values may exceed 1
``photo-info.json``                       sizes, ``shading_white``, ``albedo_excess``, the
                                          scale convention, what each file is and the
                                          ``torchiid_version`` that wrote them
``photo-params.json``                     every parameter used (the format ``--params`` reads)
``photo-reflectance.npy`` / ``-shading``  with ``ExtraOutputs(npy=True)``: float32 linear
                                          ``(H, W, 3)`` and ``(H, W)``, ``R · S == I`` to
                                          float precision
``photo-confidence.png``                  with ``ExtraOutputs(confidence=...)``: 8-bit gray,
                                          255 where the pixel's colour is trusted, 0 where it
                                          is dark or clipped (no information, shading
                                          continued smoothly), in between on the ramps of
                                          :func:`~torchiid.priors.shading_terms.pixel_confidence`
``photo-sigma.exr``                       Stage 1's last shading ``σ``, float32 linear OpenEXR
                                          (``decompose`` adds it to the set; ``ρ = I / σ``)
========================================  ====================================================

OpenEXR rather than a float TIFF for the shading: it is the interchange format for linear HDR
images (OpenCV, imageio, Pillow plug-ins, GIMP, Photoshop, Krita, Blender, Nuke, darktable and
the macOS viewer open it), it is lossless-compressed (ZIP) and its header holds metadata, here
``shading_white`` and the convention. Float TIFFs are opened by fewer viewers and often shown
clipped.

The exact pair: the EXR shading is written as the per-pixel least-squares fit
``S = Σ_c I_c R_c / Σ_c R_c²`` to the **quantised** 16-bit reflectance ``R_c``, so that
``R_png16 · S_exr`` reproduces the linear image as closely as 16-bit ``R`` allows (relative
error at most ``1 / (2 · 65535 · R_c)``); the ``.npy`` pair is the float32 result itself.

Every full-resolution conversion runs in bands of rows, so writing a 24-megapixel result needs
only its 8- and 16-bit arrays besides the layers.

One image's files are one output set (:class:`~torchiid.io.output_set.OutputSet`): they
appear together or not at all.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from torchiid._version import __version__
from torchiid.core.colour import srgb8_encode_lut
from torchiid.io.output_set import OutputError as OutputError
from torchiid.io.output_set import OutputSet as OutputSet
from torchiid.io.output_set import check_output_folder as check_output_folder
from torchiid.io.output_set import make_folders as make_folders
from torchiid.io.output_set import remove_empty_folders as remove_empty_folders
from torchiid.io.write import save_codes, save_image
from torchiid.resample import row_bands

__all__ = [
    "ExtraOutputs",
    "LayerFiles",
    "layer_file_names",
    "panel_size",
    "preview_row",
    "write_layers",
    "srgb8_from_linear",
]

#: longest side of each panel of the preview
PREVIEW_SIDE = 1024

#: what each file is, for ``-info.json``
DESCRIPTIONS = {
    "reflectance.png": "reflectance R (albedo in [0, 1]), 8-bit sRGB",
    "shading.png": "shading S / shading_white, 8-bit sRGB (values above shading_white clip)",
    "preview.png": "[image | reflectance | shading / shading_white], 8-bit sRGB, each panel at "
    f"most {PREVIEW_SIDE} px on its longer side",
    "reflectance-linear16.png": "reflectance R, 16-bit linear, unclipped",
    "shading.exr": "shading S, 32-bit float linear OpenEXR (channel Y), unclipped",
    "info.json": "sizes, scale convention and the factors to recover other conventions",
    "params.json": "every parameter used (readable with --params)",
    "reflectance.npy": "reflectance R, float32 linear (H, W, 3)",
    "shading.npy": "shading S, float32 linear (H, W)",
    "confidence.png": "pixel confidence, 8-bit gray: 255 trusted, 0 dark or clipped, "
    "in between on the ramps near dark_level and clip_level",
}

LayerFiles = dict[str, Path]


@dataclass(frozen=True)
class ExtraOutputs:
    """The optional picture and array files of :func:`write_layers`.

    Attributes:
        npy: also write the float32 ``.npy`` pair (``-reflectance.npy``, ``-shading.npy``).
        confidence: ``(1, H, W)`` in [0, 1]: written as ``-confidence.png`` when given.
    """

    npy: bool = False
    confidence: torch.Tensor | None = None


def _linear16(x: torch.Tensor) -> np.ndarray:
    """``(C, h, w)`` linear values, clipped to [0, 1], as ``(h, w, C)`` uint16 codes."""
    q = x.detach().to("cpu", torch.float32).clamp(0, 1).mul_(65535).round_()
    return q.to(torch.int32).permute(1, 2, 0).numpy().astype(np.uint16)


def srgb8_from_linear(x: torch.Tensor) -> np.ndarray:
    """``(C, H, W)`` linear values (clipped to [0, 1]) as an ``(H, W, C)`` uint8 sRGB array."""
    return srgb8_encode_lut()[_linear16(x)]


def layer_file_names(
    stem: str, *, save_npy: bool = False, save_confidence: bool = False
) -> list[str]:
    """Every file name :func:`write_layers` writes for ``stem``, in writing order."""
    keys = [
        "reflectance-linear16.png",
        "shading.exr",
        "reflectance.png",
        "shading.png",
        "preview.png",
    ]
    if save_npy:
        keys += ["reflectance.npy", "shading.npy"]
    if save_confidence:
        keys += ["confidence.png"]
    keys += ["info.json", "params.json"]
    return [f"{stem}-{k}" for k in keys]


def panel_size(height: int, width: int, side: int, minimum: int = 1) -> tuple[int, int]:
    """A preview panel's ``(h, w)``: the picture brought to at most ``side`` px, never enlarged."""
    s = min(1.0, side / max(height, width))
    return max(minimum, round(height * s)), max(minimum, round(width * s))


def preview_row(panels: list[torch.Tensor], size: tuple[int, int]) -> torch.Tensor:
    """``[a | b | c]``: ``(1|3, H, W)`` panels at ``size`` side by side, 4 px white between.

    Panels of another size are area-averaged to ``size``; gray panels are repeated in R, G, B.
    """
    row = []
    for x in panels:
        x = x.detach().to("cpu", torch.float32)
        if tuple(x.shape[-2:]) != size:
            x = F.interpolate(x[None], size=size, mode="area")[0]
        row += [x.expand(3, -1, -1), torch.ones(3, size[0], 4)]
    return torch.cat(row[:-1], dim=2)


def _write_text(text: str) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        path.write_text(text, encoding="utf-8")

    return write


def _bands(
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    white: float,
    mask: torch.Tensor | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 16-bit reflectance, the EXR shading fitted to it and the 8-bit shading view.

    Computed band by band of rows (see the module notes for the fit).
    """
    _, big_h, big_w = reflectance.shape
    r16 = np.empty((big_h, big_w, 3), np.uint16)
    s_exr = np.empty((big_h, big_w), np.float32)
    s8 = np.empty((big_h, big_w), np.uint8)
    for rows in row_bands(big_h, big_w):
        q = _linear16(reflectance[:, rows])
        r16[rows] = q
        rq = torch.from_numpy(q.astype(np.float32)).permute(2, 0, 1).div_(65535)
        i_band = image[:, rows].detach().to("cpu", torch.float32)
        num, den = (i_band * rq).sum(0), (rq * rq).sum(0)
        exact = shading[0, rows].detach().to("cpu", torch.float32)
        fit = torch.where(den > 0, num / den.clamp_min(1e-30), exact)
        if mask is not None:
            fit = fit * mask[0, rows].to("cpu", torch.float32)
        s_exr[rows] = fit.numpy()
        s8[rows] = srgb8_from_linear(exact[None] / white)[..., 0]
    return r16, s_exr, s8


def write_layers(
    out_dir: str | os.PathLike,
    stem: str,
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    *,
    shading_white: float,
    info: Mapping[str, Any] | None = None,
    params_json: str | None = None,
    mask: torch.Tensor | None = None,
    extras: ExtraOutputs | None = None,
    overwrite: bool = True,
    output_set: OutputSet | None = None,
) -> LayerFiles:
    """Write one image's layers as one output set (see the module notes for the files).

    Args:
        out_dir: the output folder (created if missing).
        stem: file name stem.
        image: ``(3, H, W)`` linear input (the preview's first panel and the EXR fit).
        reflectance: ``(3, H, W)`` linear albedo in [0, 1].
        shading: ``(1, H, W)`` linear gray shading.
        shading_white: the shading value shown as white in the viewable PNG.
        info: extra entries for ``-info.json``; its ``"files"`` (name -> description) are added
            to the list of files, for files the caller writes into the same set.
        params_json: text of ``-params.json`` (omitted when ``None``).
        mask: ``(1, H, W)`` bool; outside it the EXR shading is 0 like the layers.
        extras: the optional files (:class:`ExtraOutputs`: the ``.npy`` pair, the confidence
            picture); none by default.
        overwrite: replace existing files (else :class:`OutputError` if one exists, before
            anything is computed or written).
        output_set: add the files to this :class:`OutputSet` (of ``out_dir``) and leave it to
            the caller to add more and commit; by default the files are committed here.

    Returns:
        ``{suffix: path}`` of every file (in place, or to be put in place by the caller's
        commit).

    Raises:
        OutputError: a file cannot be written or exists without ``overwrite``; no file of
            the set was put in place (old files are unchanged).
    """
    extras = extras if extras is not None else ExtraOutputs()
    own = output_set is None
    tx = OutputSet(out_dir, overwrite=overwrite, label=stem) if own else output_set
    with tx if own else contextlib.nullcontext(tx):
        if own and not overwrite:
            _refuse_existing(tx.out, stem, extras, params_json)
        white = float(shading_white) if shading_white > 0 else 1.0
        files = _add_layers(tx, stem, (image, reflectance, shading), white, mask, extras)
        _add_records(tx, stem, files, tuple(reflectance.shape[-2:]), white, info, params_json)
        if own:
            tx.commit()
    return files


def _refuse_existing(out: Path, stem: str, extras: ExtraOutputs, params_json: str | None) -> None:
    """Raise :class:`OutputError` for the first file of the set that exists already."""
    for key in _keys(extras.npy, extras.confidence, params_json):
        if os.path.lexists(out / f"{stem}-{key}"):
            raise OutputError(f"{out / f'{stem}-{key}'} exists; pass --overwrite to replace it")


def _putter(output_set: OutputSet, stem: str, files: LayerFiles) -> Callable[..., None]:
    """``put(key, write, background=False)``: write the set's file ``<stem>-<key>``, record it.

    ``background``: on the set's writer threads (:meth:`OutputSet.write`).
    """

    def put(key: str, write: Callable[[Path], Any], background: bool = False) -> None:
        files[key] = output_set.write(f"{stem}-{key}", write, background=background)

    return put


def _codes(arr: np.ndarray) -> Callable[[Path], Any]:
    return lambda path: save_codes(path, arr)


def _exr(
    arr: np.ndarray | torch.Tensor, metadata: Mapping[str, Any] | None = None
) -> Callable[[Path], Any]:
    """A writer of ``arr`` as a float32 OpenEXR file (``metadata``: its extra attributes)."""
    return lambda path: save_image(path, arr, "exr", metadata=metadata)


def _add_layers(
    output_set: OutputSet,
    stem: str,
    layers: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    white: float,
    mask: torch.Tensor | None,
    extras: ExtraOutputs,
) -> LayerFiles:
    """Write the pictures and arrays of the set (every file but the two JSON files).

    Each file is encoded and written on the set's writer threads as soon as its array is
    ready (OpenCV and OpenEXR release the GIL), the 16-bit PNG first: at 12 MP it takes about
    a second to encode and the EXR over half of one. The set waits for them before its commit.
    """
    image, reflectance, shading = layers
    _, big_h, big_w = reflectance.shape
    r16, s_exr, s8 = _bands(image, reflectance, shading, white, mask)
    files: LayerFiles = {}
    put = _putter(output_set, stem, files)
    exr_header = {"shading_white": white, "convention": "torchiid albedo [0,1]"}
    put("reflectance-linear16.png", _codes(r16), background=True)
    put("shading.exr", _exr(s_exr, exr_header), background=True)
    put("reflectance.png", _codes(srgb8_encode_lut()[r16]), background=True)
    del r16, s_exr  # the writers hold them until they are written
    put("shading.png", _codes(s8), background=True)
    prev = preview_row(
        [image, reflectance, shading / white], panel_size(big_h, big_w, PREVIEW_SIDE)
    )
    put("preview.png", _codes(srgb8_from_linear(prev)), background=True)
    if extras.npy:
        for key, layer in (("reflectance.npy", reflectance), ("shading.npy", shading)):
            put(key, lambda p, x=layer: save_image(p, x, "npy"), background=True)
    if extras.confidence is not None:
        c = extras.confidence.detach().to("cpu", torch.float32)[0]
        put("confidence.png", _codes((c * 255).round_().to(torch.uint8).numpy()), background=True)
    return files


def _add_records(
    output_set: OutputSet,
    stem: str,
    files: LayerFiles,
    size: tuple[int, int],
    white: float,
    info: Mapping[str, Any] | None,
    params_json: str | None,
) -> None:
    """Write ``-info.json`` (and ``-params.json``) describing every file of the set."""
    big_h, big_w = size
    put = _putter(output_set, stem, files)
    record = {
        "torchiid_version": __version__,  # so a reader can interpret or migrate the files
        "size": [big_w, big_h],
        "shading_white": white,
        "convention": (
            "linear R*S = I; R is an albedo in [0, 1] whose albedo_quantile quantile of the "
            "brightest channel is 1 (pixels above moved their excess into S); S may exceed 1. "
            "(R*shading_white, S/shading_white) is the convention where the shading's 99th "
            "percentile is 1."
        ),
        **{k: v for k, v in (info or {}).items() if k != "files"},
        "files": {
            **{
                f"{stem}-{k}": DESCRIPTIONS[k]
                for k in [*files, "info.json"]
                + (["params.json"] if params_json is not None else [])
            },
            **dict((info or {}).get("files", {})),  # files the caller adds to the set
        },
    }
    put("info.json", _write_text(json.dumps(record, indent=2, allow_nan=False) + "\n"))
    if params_json is not None:
        put("params.json", _write_text(params_json))


def _keys(save_npy: bool, confidence: torch.Tensor | None, params_json: str | None) -> list[str]:
    names = layer_file_names("", save_npy=save_npy, save_confidence=confidence is not None)
    keys = [n[1:] for n in names]
    return keys if params_json is not None else [k for k in keys if k != "params.json"]
