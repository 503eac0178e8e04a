"""``torchiid decompose``: decompose image files and write the layers."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import torch

from torchiid.baselines.retinex import retinex_decomposition
from torchiid.core.device import resolve_device
from torchiid.core.exceptions import ParameterError, TorchiidError
from torchiid.io import load_image, load_mask, save_image
from torchiid.io.inputs import collect_inputs
from torchiid.io.layers import layer_file_names, write_layers
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.priors.shading_terms import pixel_confidence

log = logging.getLogger("torchiid")

RETINEX_DEFAULTS = {"threshold_gray": 0.075, "threshold_color": 1.0}


def add_parameter_options(p: argparse.ArgumentParser) -> None:
    """The options that choose the method's parameters (shared by ``decompose`` and ``eval``)."""
    p.add_argument("--preset", default="default", help="parameter preset: default or paper")
    p.add_argument("--params", type=Path, help="JSON file of parameters (over the preset)")
    p.add_argument("--variant", help="ablation variant v1..v7 or baseline1..baseline3")
    p.add_argument("--iterations", type=int, help="alternations k (overrides the preset)")
    p.add_argument(
        "--max-side", type=int, help="working resolution: longer side in px (0 = full resolution)"
    )


def params_from_args(args: argparse.Namespace) -> Parameters:
    """Parameters from --preset, --params, --variant, --iterations and --max-side."""
    params = Parameters.preset(args.preset)
    if args.params is not None:
        params = Parameters.from_json(args.params, base=params)
    if args.variant:
        params = params.variant(args.variant)
    if args.iterations is not None:
        if args.iterations < 1:
            raise ParameterError(f"--iterations must be >= 1, got {args.iterations}")
        params = params.replace(iterations=args.iterations)
    if args.max_side is not None:
        params = params.replace(max_side=args.max_side)
    return params


def output_names(stem: str, args: argparse.Namespace, params: Parameters) -> list[str]:
    """Every file name ``decompose`` writes for an input of this stem."""
    names = layer_file_names(stem, save_npy=args.save_npy, save_confidence=args.save_confidence)
    if args.save_iterations and args.method == "semantic":
        for k in range(1, params.iterations + 1):
            names += [f"{stem}-iter{k}-{layer}.png" for layer in ("sigma", "rho", "R", "S")]
    return names


def _write_outputs(
    out: Path, stem: str, loaded, result, args, params: Parameters, method: str, seconds: float
) -> None:
    """Write every layer of one image (see :mod:`torchiid.io.layers`)."""
    image = loaded.image
    mask = None if result.mask is None else result.mask[0].cpu()
    confidence = None
    if args.save_confidence:
        confidence = pixel_confidence(image[None], params.dark_level, params.clip_level)[0]
        if mask is not None:
            confidence = confidence * mask
    if method == "semantic":
        params_json = params.to_json()
    else:
        params_json = json.dumps({"method": "color_retinex", **RETINEX_DEFAULTS}, indent=2) + "\n"
    white = float(result.shading_white[0])
    info = {
        "input": str(loaded.path),
        "method": method,
        "working_size": list(reversed(result.working_size)) if result.working_size else None,
        "exif_orientation": getattr(loaded, "orientation", 1),
        "albedo_quantile": params.albedo_quantile,
        "albedo_excess": float(result.albedo_excess[0]),
        "seconds": round(seconds, 3),
        "converged": result.converged,
        "solves": [str(r) for r in result.solves],
    }
    write_layers(
        out,
        stem,
        image,
        result.reflectance[0].cpu(),
        result.shading[0].cpu(),
        shading_white=white,
        info=info,
        params_json=params_json,
        mask=mask,
        confidence=confidence,
        save_npy=args.save_npy,
    )
    if args.save_iterations and getattr(result, "iterations", None):
        for k, layers in enumerate(result.iterations, start=1):
            named = {"sigma": "sigma", "rho": "rho", "R": "reflectance", "S": "shading"}
            for name, attr in named.items():
                x = getattr(layers, attr)[0].cpu()
                if name in ("sigma", "S"):
                    x = x / torch.quantile(x.flatten(), params.view_quantile).clamp_min(1e-12)
                save_image(out / f"{stem}-iter{k}-{name}.png", x, "srgb8")


def run_decompose(args: argparse.Namespace) -> int:
    """Run the ``decompose`` subcommand; returns the exit status."""
    from tqdm import tqdm

    params = params_from_args(args)
    device = resolve_device(args.device)
    inputs = collect_inputs(args.inputs)
    stems: dict[str, Path] = {}
    for p in inputs:
        if p.stem in stems and stems[p.stem] != p:
            raise TorchiidError(
                f"two inputs would write the same outputs: {stems[p.stem]} "
                f"and {p}; rename one or run them separately"
            )
        stems[p.stem] = p
    out: Path = args.output
    if out.exists() and not out.is_dir():
        raise TorchiidError(f"{out}: output exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    shared_mask = None
    show = not args.no_progress
    failures = 0
    bar = tqdm(inputs, desc="images", unit="img", disable=not show, file=sys.stderr, leave=False)
    for path in bar:
        t0 = time.perf_counter()
        stem = path.stem
        try:
            existing = [n for n in output_names(stem, args, params) if (out / n).exists()]
            if existing and not args.overwrite:
                raise TorchiidError(f"{out / existing[0]} exists; pass --overwrite to replace it")
            loaded = load_image(path, linear=args.linear)
            image = loaded.image
            mask = loaded.mask
            if args.mask is not None:
                if shared_mask is None or shared_mask.shape[-2:] != image.shape[-2:]:
                    shared_mask = load_mask(args.mask, shape=tuple(image.shape[-2:]))
                mask = shared_mask if mask is None else (mask & shared_mask)
            batch = image[None].to(device)
            mbatch = mask[None].to(device) if mask is not None else None
            if args.method == "retinex":
                result = retinex_decomposition(batch, params, mask=mbatch, **RETINEX_DEFAULTS)
            else:
                it_bar = tqdm(
                    total=params.iterations,
                    desc=f"{stem}",
                    unit="it",
                    disable=not show,
                    file=sys.stderr,
                    leave=False,
                )

                def progress(stage: str, k: int, total: int, _bar=it_bar) -> None:
                    if stage == "iteration":
                        _bar.update(1)

                try:
                    result = decompose(
                        batch,
                        params,
                        mask=mbatch,
                        return_iterations=args.save_iterations,
                        return_stage1=False,
                        progress=progress,
                    )
                finally:
                    it_bar.close()
            seconds = time.perf_counter() - t0
            _write_outputs(out, stem, loaded, result, args, params, args.method, seconds)
            capped = [r for r in result.solves if not r.converged]
            if capped:
                worst = max(capped, key=lambda r: r.residual / r.tolerance)
                note = (
                    f"torchiid: note: {path}: {len(capped)} of {len(result.solves)} solves "
                    f"stopped at their iteration caps (worst: {worst}); see {stem}-info.json"
                )
                if show:
                    tqdm.write(note, file=sys.stderr)
                else:
                    print(note, file=sys.stderr)
            done = f"{path} -> {out}/{stem}-* ({time.perf_counter() - t0:.1f} s)"
            if show:
                tqdm.write(done, file=sys.stderr)
            else:
                log.info(done)
        except (TorchiidError, RuntimeError, MemoryError, OSError) as exc:
            failures += 1
            msg = str(exc) if isinstance(exc, TorchiidError) else f"{type(exc).__name__}: {exc}"
            if str(path) not in msg:
                msg = f"{path}: {msg}"
            print(f"torchiid: error: {msg}", file=sys.stderr)
    bar.close()
    if failures:
        print(f"torchiid: {failures} of {len(inputs)} input(s) failed", file=sys.stderr)
        return 1
    return 0
