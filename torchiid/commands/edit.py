"""``torchiid edit``: decompose one photo (or reuse a saved decomposition) and edit it.

A saved decomposition (``--from DIR``) is the folder of ``torchiid decompose`` or of an
earlier ``torchiid edit``: ``<stem>-reflectance-linear16.png`` and ``<stem>-shading.exr``
(Stage 2's ``R``, ``S``) and ``<stem>-sigma.exr`` (the last Stage 1 shading ``σ``, which the
merged components and the illumination edits need). Stage 1's reflectance is ``ρ = I / σ``
(clipped to ``[0, 1]``, 0 outside a mask): it is read from ``<stem>-rho.exr`` when that is
there (``decompose --save-stage1``) and rebuilt from the photo otherwise, to float rounding
the same layer.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torchiid.commands.common import (
    add_overwrite_and_linear,
    add_parameter_options,
    finite_float,
    params_from_args,
    say,
)

if TYPE_CHECKING:
    import torch

__all__ = ["COMBINE", "DESCRIPTION", "OPERATIONS", "add_arguments", "run"]

DESCRIPTION = (
    "Edit a photo through its reflectance and shading. Decomposes INPUT, or reuses the files "
    "of a saved decomposition (--from DIR: a folder written by `torchiid decompose` or "
    "`torchiid edit`), and writes the result and the edited layers into the output folder (-o)."
)

#: operation -> needs a mask, needs the Stage 1 layers
OPERATIONS = {
    "merge": (False, True),
    "illumination-colour": (False, True),
    "illumination-intensity": (False, True),
    "remove-texture": (True, False),
    "replace-albedo": (True, False),
    "recolour": (True, False),
    "soften-shadows": (False, False),
}

#: ``--combine`` choices (:data:`torchiid.edit.COMBINE`, named here so ``--help`` needs no torch)
COMBINE = ("mean", "e1", "e2", "max")

#: the layers each operation writes besides the result
_LAYERS = {
    "merge": ("reflectance", "shading", "C"),
    "illumination-colour": ("shading",),
    "illumination-intensity": ("shading",),
    "soften-shadows": ("shading",),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``torchiid edit``."""
    p.add_argument("operation", choices=list(OPERATIONS), help="the edit")
    p.add_argument("input", type=Path, help="the photo")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    p.add_argument(
        "--from",
        dest="from_dir",
        type=Path,
        metavar="DIR",
        help="reuse the decomposition saved in DIR by `torchiid decompose` or `torchiid edit` "
        "(<stem>-reflectance-linear16.png, <stem>-shading.exr, <stem>-sigma.exr)",
    )
    p.add_argument("--mask", type=Path, help="edit region (nonzero = inside)")
    p.add_argument(
        "--no-merge",
        action="store_true",
        help="edit Stage 2's R and S instead of the merged components (illumination-intensity "
        "is defined from both stages and always uses them)",
    )
    p.add_argument(
        "--blur",
        type=finite_float,
        help="Gaussian sigma in px of the merge's residue filter (default: 1%% of the longer "
        "side, at least 1)",
    )
    p.add_argument(
        "--tint", default="red", help="illumination-colour: name, R,G,B or #rrggbb (default red)"
    )
    p.add_argument(
        "--strength", type=finite_float, help="illumination-colour (default 1), -intensity (0.5)"
    )
    p.add_argument(
        "--percentile",
        type=finite_float,
        default=0.95,
        help="illumination-colour: the shading's quantile that marks the light regions "
        "(default %(default)s)",
    )
    p.add_argument(
        "--radius",
        type=finite_float,
        default=0.35,
        help="illumination-colour: the tint's fall-off, a fraction of the longer side "
        "(default %(default)s)",
    )
    p.add_argument(
        "--combine",
        default="mean",
        choices=COMBINE,
        help="illumination-intensity: how E1 and E2 combine (default %(default)s)",
    )
    p.add_argument(
        "--flatten",
        default="mean",
        choices=["mean", "median"],
        help="remove-texture: the region's one colour, the mean or the median of its "
        "reflectance (default %(default)s)",
    )
    p.add_argument("--texture", type=Path, help="replace-albedo: texture image")
    p.add_argument(
        "--fit",
        default="tile",
        choices=["tile", "stretch"],
        help="replace-albedo: tile the texture from the region's top-left corner (sized by "
        "--scale) or stretch it over the region's bounding box (default %(default)s)",
    )
    p.add_argument(
        "--scale",
        type=finite_float,
        default=1.0,
        help="replace-albedo: tile size factor (default %(default)s)",
    )
    p.add_argument(
        "--hue",
        type=finite_float,
        default=0.0,
        help="recolour: hue rotation in degrees (default %(default)s)",
    )
    p.add_argument(
        "--chroma",
        type=finite_float,
        default=1.0,
        help="recolour: chroma factor (default %(default)s)",
    )
    p.add_argument("--colour", help="recolour: target colour of the region")
    p.add_argument(
        "--amount",
        type=finite_float,
        default=0.5,
        help="soften-shadows: in [-10, 1]; < 0 hardens (default %(default)s)",
    )
    p.add_argument(
        "--feather",
        type=finite_float,
        default=0.0,
        help="soften-shadows: mask edge blur in px (default %(default)s)",
    )
    add_parameter_options(p)
    add_overwrite_and_linear(p)


def _read_exr(path: Path) -> torch.Tensor:
    """A float OpenEXR file as a ``(C, H, W)`` tensor."""
    import numpy as np
    import torch

    from torchiid.io.image import read_exr

    array = np.ascontiguousarray(read_exr(path)[0])
    x = torch.from_numpy(array)
    return x[None] if x.ndim == 2 else x.permute(2, 0, 1)


def _load_saved(folder: Path, source: Path, image: torch.Tensor, need_stage1: bool) -> tuple:
    """R, S, σ, ρ (``None`` without ``-sigma.exr``) of a saved decomposition, ``(1, C, H, W)``.

    ``source`` is the input file; its stem names the layers in ``folder``.

    Raises:
        TorchiidError: a file is missing, or σ is missing and ``need_stage1``.
        ImageError: the folder's ``-info.json`` records another input file (another SHA-256)
            than ``source``, or a layer has another size than ``image``.
    """
    import torch

    from torchiid.collection.image_files import saved_info
    from torchiid.collection.settings import file_sha256
    from torchiid.core.exceptions import ImageError, TorchiidError
    from torchiid.io import load_image

    stem = source.stem
    r_path = folder / f"{stem}-reflectance-linear16.png"
    s_path = folder / f"{stem}-shading.exr"
    for path in (r_path, s_path):
        if not path.is_file():
            raise TorchiidError(f"{path}: not found (--from needs the files of `decompose`)")
    info = saved_info(folder, stem) or {}
    recorded = info.get("input_sha256")  # None: not recorded (another tool, an old file)
    if isinstance(recorded, str) and recorded != file_sha256(source):
        raise ImageError(
            f"{folder}: its {stem}-* layers are the decomposition of another file than "
            f"{source} (of {info.get('input', 'a file')}, whose SHA-256 their {stem}-info.json "
            f"records); decompose {source} itself, or pass --from the folder of its own "
            "decomposition"
        )
    r = load_image(r_path, linear=True, alpha="ignore").image
    s = _read_exr(s_path)
    sig_path, rho_path = folder / f"{stem}-sigma.exr", folder / f"{stem}-rho.exr"
    sigma = _read_exr(sig_path) if sig_path.is_file() else None
    rho = _read_exr(rho_path) if sigma is not None and rho_path.is_file() else None
    if sigma is None and need_stage1:
        raise TorchiidError(
            f"{sig_path}: not found; this edit needs the Stage 1 shading, which "
            "`torchiid decompose` (the semantic method) and `torchiid edit` write"
        )
    shape = tuple(image.shape[-2:])
    for name, x in (("reflectance", r), ("shading", s), ("sigma", sigma), ("rho", rho)):
        if x is not None and tuple(x.shape[-2:]) != shape:
            raise ImageError(
                f"{folder}: the saved {name} is {x.shape[-1]}x{x.shape[-2]} px but the input is "
                f"{shape[1]}x{shape[0]} px"
            )
    if sigma is not None and rho is None:  # ρ = I / σ, as decompose made it
        rho = torch.where(sigma > 0, image / sigma.clamp_min(1e-30), 0.0).clamp_(0, 1)
    return tuple(None if x is None else x[None] for x in (r, s, sigma, rho))


def _output_names(args: argparse.Namespace, stem: str, tag: str, decomposed: bool) -> list[str]:
    from torchiid.io.layers import layer_file_names

    names = [f"{tag}.png", f"{tag}.exr", f"{tag}-info.json"]
    for layer in _LAYERS.get(args.operation, ("reflectance",)):
        names += [f"{tag}-{layer}.png", f"{tag}-{layer}.exr"]
    if decomposed:
        names += layer_file_names(stem, save_npy=False, save_confidence=False)
        names.append(f"{stem}-sigma.exr")
    return names


def _check_outputs(out: Path, names: list[str], overwrite: bool) -> None:
    from torchiid.io.layers import OutputError

    for name in names:
        target = out / name
        if target.is_dir() and not target.is_symlink():
            raise OutputError(f"{target}: is a folder; cannot replace it by an output")
        if os.path.lexists(target) and not overwrite:
            raise OutputError(f"{target} exists; pass --overwrite to replace it")


#: the options that choose how a photo is decomposed: no use with --from
_METHOD_OPTIONS = ("params", "variant", "iterations", "max_side")


def _check_numbers(args: argparse.Namespace, image: Any, texture: Any) -> None:
    """The options' numbers, checked as the edits check them (ParameterError, status 2)."""
    from torchiid.core.exceptions import ParameterError
    from torchiid.edit.common import check_edit_numbers

    try:
        check_edit_numbers(
            image, blur=args.blur, feather=args.feather, strength=args.strength,
            intensity=args.operation == "illumination-intensity", hue=args.hue,
            chroma=args.chroma, amount=args.amount, percentile=args.percentile,
            radius=args.radius, scale=args.scale, texture=texture if args.fit == "tile" else None,
        )  # fmt: skip
    except ParameterError as exc:  # its message starts with the number's name: the option's
        raise ParameterError(f"--{exc}") from None


def _decompose(args: argparse.Namespace, batch: torch.Tensor, params: Any) -> Any:
    """Decompose ``batch``; a capped solve is said in one line (``-v`` for the preset's caps)."""
    from torchiid.collection.job import solver_note
    from torchiid.core.exceptions import ConvergenceWarning, TorchiidError
    from torchiid.model import decompose

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # said below, in one line
        try:
            result = decompose(batch, params, return_stage1=True)
        except TorchiidError as exc:  # the photo's problem: named with the photo, as decompose
            if str(args.input) in str(exc):
                raise
            raise type(exc)(f"{args.input}: {exc}") from exc
    note, detail = solver_note(
        str(args.input), list(result.solves), params.converge, f"{args.input.stem}-info.json"
    )
    if note:
        say(args, f"torchiid: note: {note}")
    if detail and getattr(args, "verbose", False):
        print(f"torchiid: {detail}", file=sys.stderr)
    return result


def _apply(args, batch, r, s, sigma, rho, mask, texture) -> tuple:
    """The edit: ``(result, {layer name: tensor}, merged or None)``."""
    from torchiid import edit

    op = args.operation
    merged = None
    if sigma is not None and rho is not None and (op == "merge" or not args.no_merge):
        merged = edit.merge(batch, r, s, sigma, rho, blur=args.blur)
    er, es = (merged.reflectance, merged.shading) if merged is not None else (r, s)
    if op == "merge":
        return er * es, {"reflectance": er, "shading": es, "C": merged.c}, merged
    if op == "illumination-colour":
        strength = 1.0 if args.strength is None else args.strength
        result, new_s = edit.illumination_colour(
            er, es, args.tint, strength, percentile=args.percentile, radius=args.radius
        )
        return result, {"shading": new_s}, merged
    if op == "illumination-intensity":
        strength = 0.5 if args.strength is None else args.strength
        result, new_s = edit.illumination_intensity(
            batch, r, s, sigma, rho, strength, combine=args.combine, blur=args.blur, merged=merged
        )
        return result, {"shading": new_s}, merged
    if op == "remove-texture":
        result, new_r = edit.remove_texture(er, es, mask, flatten=args.flatten)
        return result, {"reflectance": new_r}, merged
    if op == "replace-albedo":
        result, new_r = edit.replace_albedo(er, es, mask, texture, fit=args.fit, scale=args.scale)
        return result, {"reflectance": new_r}, merged
    if op == "recolour":
        result, new_r = edit.recolour(
            er, es, mask, hue=args.hue, chroma=args.chroma, colour=args.colour
        )
        return result, {"reflectance": new_r}, merged
    result, new_s = edit.soften_shadows(er, es, args.amount, mask=mask, feather=args.feather)
    return result, {"shading": new_s}, merged


def run(args: argparse.Namespace) -> int:
    """Run ``torchiid edit``; returns the exit status (errors raise TorchiidError)."""
    from torchiid import edit
    from torchiid._version import __version__
    from torchiid.collection.settings import file_sha256
    from torchiid.core.device import resolve_device
    from torchiid.core.exceptions import ParameterError
    from torchiid.io import load_image, load_mask, save_image
    from torchiid.io.layers import OutputSet, check_output_folder, write_layers

    op = args.operation
    needs_mask, needs_stage1 = OPERATIONS[op]
    params = params_from_args(args)
    if args.from_dir is not None:
        unused = [f"--{name.replace('_', '-')}" for name in _METHOD_OPTIONS if getattr(args, name)]
        unused = (["--preset"] if args.preset != "default" else []) + unused
        if unused:
            say(
                args,
                f"torchiid: note: {', '.join(unused)} not used: --from reads the layers of "
                f"{args.from_dir} as they were decomposed",
            )
    device = resolve_device(args.device)
    out: Path = args.output
    check_output_folder(out)
    if needs_mask and args.mask is None:
        raise ParameterError(f"{op} needs --mask (nonzero = the region to edit)")
    if op == "replace-albedo" and args.texture is None:
        raise ParameterError("replace-albedo needs --texture IMAGE")
    if args.tint is not None:
        edit.parse_colour(args.tint)
    if args.colour is not None:
        edit.parse_colour(args.colour)
    image = load_image(args.input, linear=args.linear).image
    stem = args.input.stem
    mask = None
    if args.mask is not None:
        mask = load_mask(args.mask, tuple(image.shape[-2:]))[None].to(device)
    texture = None
    if args.texture is not None:
        texture = load_image(args.texture, linear=args.linear, min_side=1).image.to(device)
    _check_numbers(args, image, texture)  # before a decomposition is spent on them
    tag = f"{stem}-{op}"
    decomposed = args.from_dir is None
    _check_outputs(out, _output_names(args, stem, tag, decomposed), args.overwrite)

    t0 = time.perf_counter()
    batch = image[None].to(device)
    if decomposed:
        result = _decompose(args, batch, params)
        r, s, sigma, rho = result.reflectance, result.shading, result.sigma, result.rho
    else:
        saved = _load_saved(args.from_dir, args.input, image, needs_stage1)
        r, s, sigma, rho = (None if x is None else x.to(device) for x in saved)
    seconds_decompose = time.perf_counter() - t0
    result_img, layers, merged = _apply(args, batch, r, s, sigma, rho, mask, texture)

    white = float(edit._white(s).flatten()[0])
    info = {
        "torchiid_version": __version__,
        "input": str(args.input),
        "operation": op,
        "from": None if args.from_dir is None else str(args.from_dir),
        "merged": merged is not None,
        "options": {
            k: (str(v) if isinstance(v, Path) else v)
            for k, v in sorted(vars(args).items())
            if k not in ("command", "operation", "input", "output", "verbose", "quiet")
        },
        "shading_white": white,
        "seconds_decompose": round(seconds_decompose, 3),
        "seconds": round(time.perf_counter() - t0, 3),
    }
    with OutputSet(out, overwrite=args.overwrite, label=stem) as tx:
        res = result_img[0].detach().cpu().float()
        tx.write(f"{tag}.png", lambda p: save_image(p, res, "srgb8"))
        tx.write(f"{tag}.exr", lambda p: save_image(p, res, "exr"))
        for name, x in layers.items():
            x = x[0].detach().cpu().float()
            view = x / white if name == "shading" else x
            tx.write(f"{tag}-{name}.png", lambda p, v=view: save_image(p, v, "srgb8"))
            tx.write(f"{tag}-{name}.exr", lambda p, v=x: save_image(p, v, "exr"))
        text = json.dumps(info, indent=2, allow_nan=False) + "\n"
        tx.write(f"{tag}-info.json", lambda p: p.write_text(text, encoding="utf-8"))
        if decomposed:  # the files of `torchiid decompose`, for later `--from`
            sg = sigma[0].cpu().float()
            write_layers(
                out,
                stem,
                image,
                r[0].cpu(),
                s[0].cpu(),
                shading_white=float(result.shading_white[0]),
                info={
                    "input": str(args.input),
                    "input_sha256": file_sha256(args.input),
                    "method": "semantic",
                    "written_by": "edit",
                    "converged": result.converged,
                    "solves": [str(x) for x in result.solves],
                    "files": {f"{stem}-sigma.exr": "last Stage 1 shading sigma, float32 linear"},
                },
                params_json=params.to_json(),
                output_set=tx,
            )
            tx.write(f"{stem}-sigma.exr", lambda p: save_image(p, sg, "exr"))
        tx.commit()
    say(args, f"{args.input} -> {out}/{tag}* ({time.perf_counter() - t0:.1f} s)")
    return 0
