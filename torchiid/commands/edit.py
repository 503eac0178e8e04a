"""``torchiid edit``: decompose one photo (or reuse a saved decomposition) and edit it."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchiid import edit
from torchiid.commands.decompose import add_parameter_options, params_from_args
from torchiid.core.device import resolve_device
from torchiid.core.exceptions import ImageError, ParameterError, TorchiidError
from torchiid.io import load_image, load_mask, save_image
from torchiid.io.image import read_exr
from torchiid.io.layers import (
    OutputError,
    OutputSet,
    check_output_folder,
    layer_file_names,
    write_layers,
)

__all__ = ["OPERATIONS", "add_edit_parser", "run_edit"]

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


def add_edit_parser(sub) -> None:
    """Add the ``edit`` subcommand to the ``torchiid`` parser's subparsers."""
    p = sub.add_parser(
        "edit",
        help="edit a photo through its decomposition (relight, recolour, retexture)",
        description="Edit a photo through its reflectance and shading. Decomposes INPUT, or "
        "reuses the files of a saved decomposition (--from DIR), and writes the result and the "
        "edited layers into OUT_DIR.",
    )
    p.add_argument("operation", choices=list(OPERATIONS), help="the edit")
    p.add_argument("input", type=Path, help="the photo")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    p.add_argument(
        "--from",
        dest="from_dir",
        type=Path,
        help="reuse the decomposition saved in DIR by `torchiid decompose` or `torchiid edit` "
        "(<stem>-reflectance-linear16.png, <stem>-shading.exr; <stem>-sigma.exr and "
        "<stem>-rho.exr, written by `edit`, for merge and the illumination edits)",
    )
    p.add_argument("--mask", type=Path, help="edit region (nonzero = inside)")
    p.add_argument(
        "--no-merge",
        action="store_true",
        help="edit Stage 2's R and S instead of the merged components (illumination-intensity "
        "is defined from both stages and always uses them)",
    )
    p.add_argument("--blur", type=float, help="Gaussian sigma in px of the merge's residue filter")
    p.add_argument("--tint", default="red", help="illumination-colour: name, R,G,B or #rrggbb")
    p.add_argument(
        "--strength", type=float, help="illumination-colour (default 1), -intensity (0.5)"
    )
    p.add_argument("--percentile", type=float, default=0.95, help="light regions' quantile")
    p.add_argument(
        "--radius", type=float, default=0.35, help="tint fall-off, fraction of the longer side"
    )
    p.add_argument(
        "--combine", default="mean", choices=list(edit.COMBINE), help="how E1 and E2 combine"
    )
    p.add_argument("--flatten", default="mean", choices=["mean", "median"])
    p.add_argument("--texture", type=Path, help="replace-albedo: texture image")
    p.add_argument("--fit", default="tile", choices=["tile", "stretch"])
    p.add_argument("--scale", type=float, default=1.0, help="replace-albedo: tile size factor")
    p.add_argument("--hue", type=float, default=0.0, help="recolour: hue rotation in degrees")
    p.add_argument("--chroma", type=float, default=1.0, help="recolour: chroma factor")
    p.add_argument("--colour", help="recolour: target colour of the region")
    p.add_argument("--amount", type=float, default=0.5, help="soften-shadows: <= 1; < 0 hardens")
    p.add_argument("--feather", type=float, default=0.0, help="soften-shadows: mask edge px")
    add_parameter_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument(
        "--linear",
        action="store_true",
        help="8/16-bit input files hold linear values (default: sRGB-encoded)",
    )
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])


def _load_saved(folder: Path, stem: str, shape, need_stage1: bool):
    """R, S (and σ, ρ or ``None``) from a saved decomposition, as ``(1, C, H, W)``."""
    r_path = folder / f"{stem}-reflectance-linear16.png"
    s_path = folder / f"{stem}-shading.exr"
    for path in (r_path, s_path):
        if not path.is_file():
            raise TorchiidError(f"{path}: not found (--from needs the files of `decompose`)")
    r = load_image(r_path, linear=True, alpha="ignore").image
    s = torch.from_numpy(np.ascontiguousarray(read_exr(s_path)[0]))[None]
    sig_path, rho_path = folder / f"{stem}-sigma.exr", folder / f"{stem}-rho.exr"
    sigma = rho = None
    if sig_path.is_file() and rho_path.is_file():
        sigma = torch.from_numpy(np.ascontiguousarray(read_exr(sig_path)[0]))[None]
        rho = torch.from_numpy(np.ascontiguousarray(read_exr(rho_path)[0])).permute(2, 0, 1)
    elif need_stage1:
        raise TorchiidError(
            f"{sig_path}: not found; this edit needs the Stage 1 layers, which `torchiid edit` "
            "writes when it decomposes (run it once without --from)"
        )
    for name, x in (("reflectance", r), ("shading", s), ("sigma", sigma), ("rho", rho)):
        if x is not None and tuple(x.shape[-2:]) != tuple(shape):
            raise ImageError(
                f"{folder}: the saved {name} is {x.shape[-1]}x{x.shape[-2]} px but the input is "
                f"{shape[1]}x{shape[0]} px"
            )
    return (
        r[None],
        s[None],
        None if sigma is None else sigma[None],
        None if rho is None else rho[None],
    )


def run_edit(args: argparse.Namespace) -> int:
    """Run the ``edit`` subcommand; returns the exit status (errors raise TorchiidError)."""
    op = args.operation
    needs_mask, needs_stage1 = OPERATIONS[op]
    params = params_from_args(args)
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
    loaded = load_image(args.input, linear=args.linear)
    image = loaded.image
    stem = args.input.stem
    shape = tuple(image.shape[-2:])
    mask = None
    if args.mask is not None:
        mask = load_mask(args.mask, shape)[None]
    texture = (
        load_image(args.texture, linear=args.linear, min_side=1).image if args.texture else None
    )

    tag = f"{stem}-{op}"
    names = [f"{tag}.png", f"{tag}.exr", f"{tag}-info.json"]
    layer_names = {
        "merge": ["reflectance", "shading", "C"],
        "illumination-colour": ["shading"],
        "illumination-intensity": ["shading"],
        "soften-shadows": ["shading"],
    }.get(op, ["reflectance"])
    for layer in layer_names:
        names += [f"{tag}-{layer}.png", f"{tag}-{layer}.exr"]
    decomposed = args.from_dir is None
    if decomposed:
        names += layer_file_names(stem, save_npy=False, save_confidence=False)
        names += [f"{stem}-sigma.exr", f"{stem}-rho.exr"]
    for name in names:
        target = out / name
        if target.is_dir() and not target.is_symlink():
            raise OutputError(f"{target}: is a folder; cannot replace it by an output")
        if os.path.lexists(target) and not args.overwrite:
            raise OutputError(f"{target} exists; pass --overwrite to replace it")

    t0 = time.perf_counter()
    batch = image[None].to(device)
    if decomposed:
        from torchiid.model import decompose

        result = decompose(batch, params, return_stage1=True)
        r, s, sigma, rho = result.reflectance, result.shading, result.sigma, result.rho
    else:
        r, s, sigma, rho = _load_saved(args.from_dir, stem, shape, needs_stage1)
        r, s = r.to(device), s.to(device)
        sigma = None if sigma is None else sigma.to(device)
        rho = None if rho is None else rho.to(device)
    seconds_decompose = time.perf_counter() - t0
    mask_d = None if mask is None else mask.to(device)

    merged = None
    if sigma is not None and rho is not None and (op == "merge" or not args.no_merge):
        merged = edit.merge(batch, r, s, sigma, rho, blur=args.blur)
    er, es = (merged.reflectance, merged.shading) if merged is not None else (r, s)
    layers: dict[str, torch.Tensor] = {}
    if op == "merge":
        result_img = er * es
        layers = {"reflectance": er, "shading": es, "C": merged.c}
    elif op == "illumination-colour":
        strength = 1.0 if args.strength is None else args.strength
        result_img, new_s = edit.illumination_colour(
            er, es, args.tint, strength, percentile=args.percentile, radius=args.radius
        )
        layers = {"shading": new_s}
    elif op == "illumination-intensity":
        strength = 0.5 if args.strength is None else args.strength
        result_img, new_s = edit.illumination_intensity(
            batch, r, s, sigma, rho, strength, combine=args.combine, blur=args.blur, merged=merged
        )
        layers = {"shading": new_s}
    elif op == "remove-texture":
        result_img, new_r = edit.remove_texture(er, es, mask_d, flatten=args.flatten)
        layers = {"reflectance": new_r}
    elif op == "replace-albedo":
        result_img, new_r = edit.replace_albedo(
            er, es, mask_d, texture.to(device), fit=args.fit, scale=args.scale
        )
        layers = {"reflectance": new_r}
    elif op == "recolour":
        result_img, new_r = edit.recolour(
            er, es, mask_d, hue=args.hue, chroma=args.chroma, colour=args.colour
        )
        layers = {"reflectance": new_r}
    else:
        result_img, new_s = edit.soften_shadows(
            er, es, args.amount, mask=mask_d, feather=args.feather
        )
        layers = {"shading": new_s}

    white = float(edit._white(s).flatten()[0])
    info = {
        "input": str(args.input),
        "operation": op,
        "from": None if args.from_dir is None else str(args.from_dir),
        "merged": merged is not None,
        "options": {
            k: (str(v) if isinstance(v, Path) else v)
            for k, v in sorted(vars(args).items())
            if k not in ("command", "operation", "input", "output", "verbose")
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
        if decomposed:
            write_layers(
                out,
                stem,
                image,
                r[0].cpu(),
                s[0].cpu(),
                shading_white=float(result.shading_white[0]),
                info={"input": str(args.input), "method": "semantic", "written_by": "edit"},
                params_json=params.to_json(),
                output_set=tx,
            )
            sg, rh = sigma[0].cpu().float(), rho[0].cpu().float()
            tx.write(f"{stem}-sigma.exr", lambda p: save_image(p, sg, "exr"))
            tx.write(f"{stem}-rho.exr", lambda p: save_image(p, rh, "exr"))
        tx.commit()
    print(f"{args.input} -> {out}/{tag}* ({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    return 0
