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
                                          scale convention and what each file is
``photo-params.json``                     every parameter used (the format ``--params`` reads)
``photo-reflectance.npy`` / ``-shading``  with ``save_npy``: float32 linear ``(H, W, 3)`` and
                                          ``(H, W)``, ``R · S == I`` to float precision
``photo-confidence.png``                  with ``save_confidence``: 8-bit gray, 255 where the
                                          pixel's colour is trusted, 0 where it is dark or
                                          clipped (no information, shading continued smoothly)
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
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from torchiid.core.colour import srgb8_encode_lut
from torchiid.io.image import save_codes, save_image
from torchiid.resample import row_bands

__all__ = ["LayerFiles", "layer_file_names", "write_layers", "srgb8_from_linear"]

#: longest side of each panel of the preview
PREVIEW_SIDE = 1024

#: what each file is, for ``-info.json`` and the README
DESCRIPTIONS = {
    "reflectance.png": "reflectance R (albedo in [0, 1]), 8-bit sRGB",
    "shading.png": "shading S / shading_white, 8-bit sRGB (values above shading_white clip)",
    "preview.png": "[image | reflectance | shading / shading_white], 8-bit sRGB, downscaled",
    "reflectance-linear16.png": "reflectance R, 16-bit linear, unclipped",
    "shading.exr": "shading S, 32-bit float linear OpenEXR (channel Y), unclipped",
    "info.json": "sizes, scale convention and the factors to recover other conventions",
    "params.json": "every parameter used (readable with --params)",
    "reflectance.npy": "reflectance R, float32 linear (H, W, 3)",
    "shading.npy": "shading S, float32 linear (H, W)",
    "confidence.png": "pixel confidence, 8-bit gray: 255 trusted, 0 dark or clipped",
}

LayerFiles = dict[str, Path]


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


def _preview_panel(x: torch.Tensor) -> torch.Tensor:
    h, w = x.shape[-2:]
    s = PREVIEW_SIDE / max(h, w)
    if s >= 1:
        return x
    size = (max(1, round(h * s)), max(1, round(w * s)))
    return F.interpolate(x[None], size=size, mode="area")[0]


def _write_json(path: Path, data: Mapping[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)


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
    confidence: torch.Tensor | None = None,
    save_npy: bool = False,
) -> LayerFiles:
    """Write one image's layers (see the module notes for the files).

    Args:
        out_dir: the output folder (created if missing).
        stem: file name stem.
        image: ``(3, H, W)`` linear input (the preview's first panel and the EXR fit).
        reflectance: ``(3, H, W)`` linear albedo in [0, 1].
        shading: ``(1, H, W)`` linear gray shading.
        shading_white: the shading value shown as white in the viewable PNG.
        info: extra entries for ``-info.json``.
        params_json: text of ``-params.json`` (omitted when ``None``).
        mask: ``(1, H, W)`` bool; outside it the EXR shading is 0 like the layers.
        confidence: ``(1, H, W)`` in [0, 1]: written as ``-confidence.png`` when given.
        save_npy: also write the float32 ``.npy`` pair.

    Returns:
        ``{suffix: path}`` of every file written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _, big_h, big_w = reflectance.shape
    r16 = np.empty((big_h, big_w, 3), np.uint16)
    s_exr = np.empty((big_h, big_w), np.float32)
    s8 = np.empty((big_h, big_w), np.uint8)
    white = float(shading_white) if shading_white > 0 else 1.0
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
    files: LayerFiles = {}

    def name(key: str) -> Path:
        files[key] = out / f"{stem}-{key}"
        return files[key]

    save_codes(name("reflectance-linear16.png"), r16)
    save_image(
        name("shading.exr"),
        s_exr,
        "exr",
        metadata={"shading_white": white, "convention": "torchiid albedo [0,1]"},
    )
    r8 = srgb8_encode_lut()[r16]
    del r16
    save_codes(name("reflectance.png"), r8)
    save_codes(name("shading.png"), s8)
    panels = [
        _preview_panel(x.detach().to("cpu", torch.float32)).expand(3, -1, -1)
        for x in (image, reflectance, shading / white)
    ]
    sep = torch.ones(3, panels[0].shape[1], 4)
    prev = torch.cat([panels[0], sep, panels[1], sep, panels[2]], dim=2)
    save_codes(name("preview.png"), srgb8_from_linear(prev))
    if save_npy:
        save_image(name("reflectance.npy"), reflectance, "npy")
        save_image(name("shading.npy"), shading, "npy")
    if confidence is not None:
        conf = (confidence.detach().to("cpu", torch.float32)[0] * 255).round_().to(torch.uint8)
        save_codes(name("confidence.png"), conf.numpy())
    record = {
        "size": [big_w, big_h],
        "shading_white": white,
        "convention": (
            "linear R*S = I; R is an albedo in [0, 1] whose albedo_quantile quantile of the "
            "brightest channel is 1 (pixels above moved their excess into S); S may exceed 1. "
            "(R*shading_white, S/shading_white) is the convention where the shading's 99th "
            "percentile is 1."
        ),
        **(dict(info) if info else {}),
        "files": {
            f"{stem}-{k}": DESCRIPTIONS[k]
            for k in [*files, "info.json"] + (["params.json"] if params_json is not None else [])
        },
    }
    _write_json(name("info.json"), record)
    if params_json is not None:
        target = name("params.json")
        tmp = target.with_name(f".{target.name}.tmp")
        tmp.write_text(params_json)
        os.replace(tmp, target)
    return files
