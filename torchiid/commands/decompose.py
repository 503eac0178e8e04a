"""``torchiid decompose``: decompose image files and write the layers."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

from torchiid.baselines.retinex import retinex_decomposition
from torchiid.core.device import resolve_device
from torchiid.core.exceptions import ImageError, ParameterError, TorchiidError
from torchiid.core.stats import image_quantile
from torchiid.io import load_image, load_mask, save_image
from torchiid.io.inputs import collect_inputs
from torchiid.io.layers import (
    OutputError,
    OutputSet,
    check_output_folder,
    layer_file_names,
    write_layers,
)
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
    if getattr(args, "save_stage1", False) and args.method == "semantic":
        names += [f"{stem}-sigma.exr", f"{stem}-rho.exr"]
    if args.save_iterations and args.method == "semantic":
        for k in range(1, params.iterations + 1):
            names += [f"{stem}-iter{k}-{layer}.png" for layer in ("sigma", "rho", "R", "S")]
    return names


def _write_outputs(
    tx: OutputSet, stem: str, loaded, result, args, params: Parameters, seconds: float
) -> None:
    """Write every layer of one image into the output set ``tx`` (:mod:`torchiid.io.layers`)."""
    image = loaded.image
    mask = None if result.mask is None else result.mask[0].cpu()
    confidence = None
    if args.save_confidence:
        confidence = pixel_confidence(image[None], params.dark_level, params.clip_level)[0]
        if mask is not None:
            confidence = confidence * mask
    if args.method == "semantic":
        params_json = params.to_json()
    else:
        params_json = json.dumps({"method": "color_retinex", **RETINEX_DEFAULTS}, indent=2) + "\n"
    white = float(result.shading_white[0])
    info = {
        "input": str(loaded.path),
        "method": args.method,
        "working_size": list(reversed(result.working_size)) if result.working_size else None,
        "exif_orientation": getattr(loaded, "orientation", 1),
        "albedo_quantile": params.albedo_quantile,
        "albedo_excess": float(result.albedo_excess[0]),
        "seconds": round(seconds, 3),
        "converged": result.converged,
        "solves": [str(r) for r in result.solves],
        "files": {},
    }
    if getattr(args, "save_stage1", False) and result.sigma is not None:
        info["files"][f"{stem}-sigma.exr"] = "last Stage 1 shading sigma, float32 linear OpenEXR"
        info["files"][f"{stem}-rho.exr"] = "last Stage 1 reflectance rho, float32 linear OpenEXR"
    if args.save_iterations and getattr(result, "iterations", None):
        for k in range(1, len(result.iterations) + 1):
            for name in ("sigma", "rho", "R", "S"):
                info["files"][f"{stem}-iter{k}-{name}.png"] = (
                    f"alternation {k}'s {name} at the working resolution, 8-bit sRGB"
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
        confidence=confidence,
        save_npy=args.save_npy,
        output_set=tx,
    )
    if getattr(args, "save_stage1", False) and result.sigma is not None:
        # the last Stage 1 layers, exact, for `torchiid edit --from` (merge, illumination)
        sg, rh = result.sigma[0].cpu(), result.rho[0].cpu()
        tx.write(f"{stem}-sigma.exr", lambda p: save_image(p, sg, "exr"))
        tx.write(f"{stem}-rho.exr", lambda p: save_image(p, rh, "exr"))
    if args.save_iterations and getattr(result, "iterations", None):
        named = {"sigma": "sigma", "rho": "rho", "R": "reflectance", "S": "shading"}
        for k, layers in enumerate(result.iterations, start=1):
            for name, attr in named.items():
                x = getattr(layers, attr)[0].cpu()
                if name in ("sigma", "S"):
                    x = x / image_quantile(x[None], params.view_quantile).clamp_min(1e-12)[0]
                tx.write(f"{stem}-iter{k}-{name}.png", lambda p, x=x: save_image(p, x, "srgb8"))


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _error_message(path: Path, exc: Exception) -> str:
    """One line naming the input and the problem."""
    if isinstance(exc, TorchiidError):
        msg = _one_line(str(exc))
    elif isinstance(exc, OSError):
        where = f" {exc.filename}" if exc.filename else ""
        msg = f"cannot access{where} ({exc.strerror or _one_line(str(exc))})"
    elif isinstance(exc, (RuntimeError, MemoryError)):
        msg = f"{type(exc).__name__}: {_one_line(str(exc))}"
    else:
        msg = (
            f"internal error ({type(exc).__name__}: {_one_line(str(exc))}); "
            "rerun with --verbose for the traceback"
        )
    return msg if str(path) in msg else f"{path}: {msg}"


def _unique_inputs(inputs: list[Path]) -> list[Path]:
    """The inputs without repeats of the same file; raises if two would write the same outputs."""
    seen: set[Path] = set()
    stems: dict[str, Path] = {}
    unique = []
    for p in inputs:
        key = Path(os.path.abspath(p))
        if key in seen:
            continue
        seen.add(key)
        if p.stem in stems:
            raise TorchiidError(
                f"two inputs would write the same outputs: {stems[p.stem]} "
                f"and {p}; rename one or run them separately"
            )
        stems[p.stem] = p
        unique.append(p)
    return unique


def run_decompose(args: argparse.Namespace) -> int:
    """Run the ``decompose`` subcommand; returns the exit status.

    Everything that concerns the whole run (parameters, device, the output folder, the input
    list, the ``--mask`` file) is checked before any image is decomposed and raises
    :class:`TorchiidError` (exit status 2). Then every input is processed on its own: a bad
    input, or an output that cannot be written, is reported in one line naming the file, the
    other inputs go on, and the status is 1. Each image's files are put in place together
    (:class:`~torchiid.io.layers.OutputSet`); the output folder is created with the first of
    them. An interrupt ends the run with status 130; the interrupted image leaves nothing.
    """
    from tqdm import tqdm

    params = params_from_args(args)
    device = resolve_device(args.device)
    out: Path = args.output
    check_output_folder(out)
    inputs = _unique_inputs(collect_inputs(args.inputs))
    shared_mask = load_mask(args.mask) if args.mask is not None else None
    show = not args.no_progress

    def say(message: str) -> None:
        if show:
            tqdm.write(message, file=sys.stderr)  # above the progress bar, not into its line
        else:
            print(message, file=sys.stderr)

    failures = written = 0
    bar = tqdm(inputs, desc="images", unit="img", disable=not show, file=sys.stderr, leave=False)
    tx: OutputSet | None = None  # the set of the image being processed
    path = out
    try:
        for path in bar:
            t0 = time.perf_counter()
            stem = path.stem
            try:
                tx = OutputSet(out, overwrite=args.overwrite, label=stem)
                for name in output_names(stem, args, params):
                    target = out / name
                    if target.is_dir() and not target.is_symlink():
                        raise OutputError(f"{target}: is a folder; cannot replace it by an output")
                    if os.path.lexists(target) and not args.overwrite:
                        raise OutputError(f"{target} exists; pass --overwrite to replace it")
                loaded = load_image(path, linear=args.linear)
                image = loaded.image
                mask = loaded.mask
                if shared_mask is not None:
                    if shared_mask.shape[-2:] != image.shape[-2:]:
                        (mh, mw), (h, w) = shared_mask.shape[-2:], image.shape[-2:]
                        raise ImageError(
                            f"{path}: is {w}x{h} px but the mask {args.mask} is {mw}x{mh} px"
                        )
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
                            return_stage1=getattr(args, "save_stage1", False),
                            progress=progress,
                        )
                    finally:
                        it_bar.close()
                seconds = time.perf_counter() - t0
                with tx:
                    _write_outputs(tx, stem, loaded, result, args, params, seconds)
                    tx.commit()
                written, tx = written + 1, None
                capped = [r for r in result.solves if not r.converged]
                if capped:
                    worst = max(capped, key=lambda r: r.residual / r.tolerance)
                    say(
                        f"torchiid: note: {path}: {len(capped)} of {len(result.solves)} solver "
                        "runs stopped at their iteration caps before their tolerance (the "
                        "default preset caps them on purpose; largest residual "
                        f"{worst.residual:.1g} against {worst.tolerance:g}); details in "
                        f"{stem}-info.json"
                    )
                done = f"{path} -> {out}/{stem}-* ({time.perf_counter() - t0:.1f} s)"
                if show:
                    tqdm.write(done, file=sys.stderr)
                else:
                    log.info(done)
            except Exception as exc:  # noqa: BLE001 - one bad input must not stop the batch
                failures, tx = failures + 1, None
                say(f"torchiid: error: {_error_message(path, exc)}")
                if not isinstance(exc, TorchiidError):
                    log.info("the error above came from here:", exc_info=exc)
    except KeyboardInterrupt:
        bar.close()
        where = ""
        if tx is not None and tx.committed:  # it arrived while the set was put in place
            written += 1
        elif tx is not None:
            where = f" while processing {path} (nothing of it was written)"
        print(
            f"torchiid: interrupted{where}; {written} of {len(inputs)} input(s) written",
            file=sys.stderr,
        )
        return 130
    bar.close()
    if failures:
        print(f"torchiid: {failures} of {len(inputs)} input(s) failed", file=sys.stderr)
        return 1
    return 0
