"""``torchiid decompose``: decompose image files and write the layers."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import torch

from torchiid.core.exceptions import ParameterError, TorchiidError
from torchiid.io import load_image, load_mask, save_image
from torchiid.params import Parameters

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
    names = [
        f"{stem}-reflectance.png",
        f"{stem}-shading.png",
        f"{stem}-preview.png",
        f"{stem}-params.json",
    ]
    if args.save_linear:
        names += [f"{stem}-reflectance-linear16.png", f"{stem}-shading-linear16.png"]
    if args.save_npy:
        names += [f"{stem}-reflectance.npy", f"{stem}-shading.npy"]
    if args.save_iterations and args.method == "semantic":
        for k in range(1, params.iterations + 1):
            names += [f"{stem}-iter{k}-{layer}.png" for layer in ("sigma", "rho", "R", "S")]
    return names


def _preview(image: torch.Tensor, refl: torch.Tensor, shading: torch.Tensor) -> torch.Tensor:
    """``[I | R | S]`` side by side, linear, ``(3, H, 3W + 2 gaps)``."""
    gap = image.new_ones(3, image.shape[1], 4)
    return torch.cat([image, gap, refl, gap, shading.expand(3, -1, -1)], dim=2)


def _write_outputs(
    out: Path, stem: str, image: torch.Tensor, result, args, params, method: str
) -> None:
    """Write every layer of one image atomically (see :func:`output_names`)."""
    refl = result.reflectance[0].cpu()
    shad = result.shading[0].cpu()
    save_image(out / f"{stem}-reflectance.png", refl, "srgb8")
    save_image(out / f"{stem}-shading.png", shad, "srgb8")
    save_image(out / f"{stem}-preview.png", _preview(image, refl, shad), "srgb8")
    if args.save_linear:
        save_image(out / f"{stem}-reflectance-linear16.png", refl, "linear16")
        save_image(out / f"{stem}-shading-linear16.png", shad, "linear16")
    if args.save_npy:
        save_image(out / f"{stem}-reflectance.npy", refl, "npy")
        save_image(out / f"{stem}-shading.npy", shad, "npy")
    if args.save_iterations and getattr(result, "iterations", None):
        for k, layers in enumerate(result.iterations, start=1):
            for name in ("sigma", "rho", "R", "S"):
                save_image(
                    out / f"{stem}-iter{k}-{name}.png", getattr(layers, name)[0].cpu(), "srgb8"
                )
    target = out / f"{stem}-params.json"
    if method == "semantic":
        params.to_json(target)  # the same format --params reads back
    else:
        text = json.dumps({"method": "color_retinex", **RETINEX_DEFAULTS}, indent=2) + "\n"
        tmp = target.with_name(f".{target.name}.tmp")
        tmp.write_text(text)
        os.replace(tmp, target)


def run_decompose(args: argparse.Namespace) -> int:
    """Run the ``decompose`` subcommand; returns the exit status."""
    from tqdm import tqdm

    from torchiid.cli import collect_inputs, resolve_device
    from torchiid.model import decompose

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
                from torchiid.baselines.retinex import color_retinex

                refl, shad = color_retinex(batch, mask=mbatch, **RETINEX_DEFAULTS)
                result = SimpleNamespace(reflectance=refl, shading=shad, iterations=())
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
                        progress=progress,
                    )
                finally:
                    it_bar.close()
            _write_outputs(out, stem, image, result, args, params, args.method)
            done = f"{path} -> {out}/{stem}-*.png ({time.perf_counter() - t0:.1f} s)"
            if show:
                tqdm.write(done, file=sys.stderr)
            else:
                log.info(done)
        except TorchiidError as exc:
            failures += 1
            msg = str(exc)
            print(f"torchiid: error: {msg}", file=sys.stderr)
    bar.close()
    if failures:
        print(f"torchiid: {failures} of {len(inputs)} input(s) failed", file=sys.stderr)
        return 1
    return 0
