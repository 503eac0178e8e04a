"""An image's output files: their names, their writing and whether those there are complete.

:func:`output_names` lists every file ``decompose`` writes for an image, :func:`write_outputs`
writes them into the image's :class:`~torchiid.io.layers.OutputSet` (with ``-info.json``
saying what they hold), and :func:`recorded` tells files of this very decomposition (same
input, parameters and mask) from others.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from torchiid._version import __version__
from torchiid.collection.settings import RETINEX_DEFAULTS, RunSettings
from torchiid.core.stats import image_quantile
from torchiid.io import save_image
from torchiid.io.layers import ExtraOutputs, OutputSet, layer_file_names, write_layers
from torchiid.params import Parameters
from torchiid.pipeline.results import solve_record
from torchiid.priors.shading_terms import pixel_confidence

__all__ = ["output_names", "recorded", "write_outputs"]


def output_names(stem: str, settings: Any, params: Parameters) -> list[str]:
    """Every file name ``decompose`` writes for an image of this stem.

    ``settings`` is a :class:`RunSettings` or the command's ``argparse.Namespace`` (the same
    attribute names).
    """
    names = layer_file_names(
        stem, save_npy=settings.save_npy, save_confidence=settings.save_confidence
    )
    if settings.method == "semantic":  # σ always: every `torchiid edit --from` needs it
        names.append(f"{stem}-sigma.exr")
        if getattr(settings, "save_stage1", False):
            names.append(f"{stem}-rho.exr")
    if settings.save_iterations and settings.method == "semantic":
        for k in range(1, params.iterations + 1):
            names += [f"{stem}-iter{k}-{layer}.png" for layer in ("sigma", "rho", "R", "S")]
    return names


def saved_info(out_dir: Path, stem: str) -> dict | None:
    """The ``<stem>-info.json`` in ``out_dir`` (``None``: missing, unreadable or not a record)."""
    try:
        info = json.loads((out_dir / f"{stem}-info.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def recorded(
    out_dir: Path, names: list[str], stem: str, sha: str, phash: str, mask_sha: str | None
) -> bool:
    """The outputs there are complete and record this input, its own mask and these parameters."""
    if not all(os.path.isfile(out_dir / n) for n in names):
        return False
    info = saved_info(out_dir, stem)
    return (
        info is not None
        and info.get("input_sha256") == sha
        and info.get("params_hash") == phash
        and info.get("mask_sha256") == mask_sha
    )


def write_outputs(
    tx: OutputSet,
    stem: str,
    loaded: Any,
    result: Any,
    settings: RunSettings,
    params: Parameters,
    seconds: float,
    extra: dict,
) -> None:
    """Write every layer of one image into the output set ``tx`` (:mod:`torchiid.io.layers`)."""
    image = loaded.image
    mask = None if result.mask is None else result.mask[0].cpu()
    confidence = None
    if settings.save_confidence:
        sh = params.shading
        confidence = pixel_confidence(image[None], sh.dark_level, sh.clip_level)[0]
        if mask is not None:
            confidence = confidence * mask
    if settings.method == "semantic":
        params_json = params.to_json()
    else:
        retinex = {"torchiid_version": __version__, "method": "color_retinex", **RETINEX_DEFAULTS}
        params_json = json.dumps(retinex, indent=2) + "\n"
    white = float(result.shading_white[0])
    sigma = settings.method == "semantic" and result.sigma is not None
    rho = sigma and settings.save_stage1
    iterations = settings.save_iterations and getattr(result, "iterations", None)
    info = {
        "input": str(loaded.path),
        "method": settings.method,
        "working_size": list(reversed(result.working_size)) if result.working_size else None,
        "exif_orientation": getattr(loaded, "orientation", 1),
        "negatives_set_to_zero": getattr(loaded, "negatives", 0),
        **solve_record(result, params, seconds),
        **extra,
        "files": {},
    }
    if sigma:
        info["files"][f"{stem}-sigma.exr"] = (
            "last Stage 1 shading sigma, float32 linear OpenEXR (rho = I / sigma)"
        )
    if rho:
        info["files"][f"{stem}-rho.exr"] = "last Stage 1 reflectance rho, float32 linear OpenEXR"
    if iterations:
        coarse = {r.alternation: r.size for r in result.solves if r.size is not None}
        for k in range(1, len(result.iterations) + 1):
            where = "at the working resolution"
            if k in coarse:  # an alternation before the last, with coarse_scale below 1
                h, w = coarse[k]
                where = f"solved at {w}x{h}, brought up to the working resolution"
            for name in ("sigma", "rho", "R", "S"):
                info["files"][f"{stem}-iter{k}-{name}.png"] = (
                    f"alternation {k}'s {name} {where}, 8-bit sRGB"
                )
    write_layers(
        tx.out,
        stem,
        image,
        result.reflectance[0].cpu(),
        result.shading[0].cpu(),
        shading_white=white,
        info=info,
        params_json=params_json,
        mask=mask,
        extras=ExtraOutputs(npy=settings.save_npy, confidence=confidence),
        output_set=tx,
    )
    if sigma:
        # the last Stage 1 shading, exact, for `torchiid edit --from` (merge, illumination);
        # its reflectance is the photo divided by it, rebuilt there unless written here
        sg = result.sigma[0].cpu()
        tx.write(f"{stem}-sigma.exr", lambda p: save_image(p, sg, "exr"), background=True)
    if rho:
        rh = result.rho[0].cpu()
        tx.write(f"{stem}-rho.exr", lambda p: save_image(p, rh, "exr"), background=True)
    if iterations:
        named = {"sigma": "sigma", "rho": "rho", "R": "reflectance", "S": "shading"}
        for k, layers in enumerate(result.iterations, start=1):
            for name, attr in named.items():
                x = getattr(layers, attr)[0].cpu()
                if name in ("sigma", "S"):
                    x = x / image_quantile(x[None], params.output.view_quantile).clamp_min(1e-12)[0]
                tx.write(f"{stem}-iter{k}-{name}.png", lambda p, x=x: save_image(p, x, "srgb8"))
