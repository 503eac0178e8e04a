"""``torchiid decompose``: decompose image files and write the layers.

The work is :func:`torchiid.collection.run_collection`; this module reads the options, checks
everything that concerns the whole run before any image, and prints.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
from pathlib import Path

from torchiid.collection import (
    MANIFEST_NAME,
    RETINEX_DEFAULTS,
    ImageResult,
    Plan,
    Progress,
    RunInterrupted,
    RunSettings,
    RunSummary,
    file_sha256,
    output_names,
    run_collection,
)
from torchiid.core.device import resolve_device
from torchiid.core.exceptions import ParameterError, TorchiidError
from torchiid.io import load_mask
from torchiid.io.inputs import list_inputs, unique_keys
from torchiid.io.layers import check_output_folder
from torchiid.model import decompose
from torchiid.params import Parameters

__all__ = [
    "RETINEX_DEFAULTS",
    "add_parameter_options",
    "output_names",
    "params_from_args",
    "run_decompose",
]

log = logging.getLogger("torchiid")


def add_parameter_options(p: argparse.ArgumentParser) -> None:
    """The options that choose the method's parameters (shared by ``decompose`` and ``eval``)."""
    p.add_argument(
        "--preset",
        default="default",
        help=(
            "parameter preset: default, print (photos of printed matter: documents, "
            "labels), paper or converged (every solve to tolerance)"
        ),
    )
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


def _duration(seconds: float) -> str:
    seconds = round(seconds)
    if seconds < 60:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes} min {seconds} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes} min"


class _Printer:
    """Prints what a run does: messages above the progress bar, the bar, the summary."""

    def __init__(self, args: argparse.Namespace, out: Path) -> None:
        self.show = not args.no_progress
        self.out = out
        self.bar = None

    def say(self, message: str) -> None:
        if self.bar is not None:
            from tqdm import tqdm

            tqdm.write(message, file=sys.stderr)  # above the progress bar, not into its line
        else:
            print(message, file=sys.stderr)

    def planned(self, plan: Plan, summary: RunSummary) -> None:
        from tqdm import tqdm

        for item, record in plan.failed_before:
            self.say(
                f"torchiid: note: {item.path}: failed before ({record.get('message')}); "
                "--retry-failed tries it again"
            )
        if self.show and plan.todo:
            self.bar = tqdm(
                total=len(plan.todo),
                desc="images",
                unit="img",
                file=sys.stderr,
                leave=False,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} "
                "[{elapsed}<{remaining}{postfix}]",
            )

    def result(self, result: ImageResult, progress: Progress) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(f"{progress.per_minute:.1f} images/min", refresh=False)
            self.bar.update(1)
        if not result.ok:
            self.say(f"torchiid: error: {result.message}")
            return
        if result.note:
            self.say(f"torchiid: note: {result.note}")
        how = "complete files found" if result.recovered else f"{result.seconds:.1f} s"
        line = f"{result.path} -> {self.out}/{result.key}-* ({how})"
        if progress.to_process > 1:
            eta = progress.eta
            line += (
                f"; {progress.processed} of {progress.to_process}, "
                f"{progress.per_minute:.1f} images/minute"
                + (f", {_duration(eta)} left" if eta is not None and eta > 0 else "")
            )
        if self.bar is not None:
            self.say(line)
        else:
            log.info(line)

    def retrying(self, job, how: str) -> None:
        self.say(f"torchiid: note: {job.path}: its worker process died ({how}); trying it again")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _settings(args: argparse.Namespace, params: Parameters, out: Path) -> RunSettings:
    mask_sha = None
    if args.mask is not None:
        load_mask(args.mask)  # a missing, unreadable or empty mask is a set-up error
        mask_sha = file_sha256(args.mask)
    threads = getattr(args, "threads", None)
    if threads is not None and threads < 1:
        raise TorchiidError(f"--threads must be >= 1, got {threads}")
    return RunSettings(
        out=out,
        params=params,
        method=args.method,
        linear=args.linear,
        device=args.device,
        overwrite=args.overwrite,
        save_npy=args.save_npy,
        save_confidence=args.save_confidence,
        save_stage1=getattr(args, "save_stage1", False),
        save_iterations=args.save_iterations,
        mask=args.mask,
        mask_sha256=mask_sha,
        threads=threads,
        redo=getattr(args, "redo", False),
    )


def run_decompose(args: argparse.Namespace) -> int:
    """Run the ``decompose`` subcommand; returns the exit status.

    Everything that concerns the whole run (parameters, device, the output folder, the input
    list, the ``--mask`` file, the output folder's lock, and then, when there is work, the
    model in this process or in each worker process) is checked before any image is decomposed
    and raises :class:`TorchiidError` (exit status 2; nothing is recorded as failed). Then
    every input is processed on its own: a bad input, or an output that cannot be written, is
    reported in one line naming the file, the other inputs go on, and the status is 1. Each
    image's files are put in place together (:class:`~torchiid.io.layers.OutputSet`) and
    recorded in the manifest. An interrupt ends the run with status 130; the interrupted images
    leave nothing (on Dask, tasks still running after the wait are named: they may still write
    their files).
    """
    params = params_from_args(args)
    device = resolve_device(args.device)
    workers = getattr(args, "workers", None)
    scheduler = getattr(args, "dask_scheduler", None)
    retries = getattr(args, "retries", 1)
    if workers is not None and workers < 1:
        raise TorchiidError(f"--workers must be >= 1, got {workers}")
    if workers is not None and scheduler is not None:
        raise TorchiidError("--workers and --dask-scheduler exclude each other")
    if retries < 0:
        raise TorchiidError(f"--retries must be >= 0, got {retries}")
    out: Path = args.output
    check_output_folder(out)
    lists = getattr(args, "list", None) or []
    if not args.inputs and not lists:
        raise TorchiidError("no inputs: name image files, folders or globs, or --list FILE")
    items = unique_keys(
        list_inputs(
            args.inputs, recursive=getattr(args, "recursive", False), lists=lists, exclude=[out]
        )
    )
    settings = _settings(args, params, out)
    if scheduler is not None:  # the workers may run in another folder, or elsewhere
        absolute = {"out": Path(os.path.abspath(out))}
        if args.mask is not None:
            absolute["mask"] = Path(os.path.abspath(args.mask))
        settings = dataclasses.replace(settings, **absolute)
    if scheduler is None and workers is None:
        settings = dataclasses.replace(settings, device=str(device))
    printer = _Printer(args, args.output)
    try:
        summary = run_collection(
            items,
            settings,
            workers=workers,
            scheduler=scheduler,
            retries=retries,
            retry_failed=getattr(args, "retry_failed", False),
            redo=getattr(args, "redo", False),
            decompose_fn=decompose if (workers is None and scheduler is None) else None,
            show_progress=printer.show,
            reporter=printer,
        )
    except RunInterrupted as stop:
        printer.close()
        s = stop.summary
        where = ""
        if s.interrupted_on:
            names = ", ".join(s.interrupted_on)
            where = f" while processing {names} (nothing of it was written)"
        skipped = f", {s.skipped_done} skipped as done before" if s.skipped_done else ""
        print(
            f"torchiid: interrupted{where}; {s.done} of {s.total} input(s) written{skipped}",
            file=sys.stderr,
        )
        if s.left_running:
            print(
                f"torchiid: note: {len(s.left_running)} image(s) were still running on the "
                f"cluster and may still write their files into {args.output} (their tasks are "
                f"cancelled, but Dask cannot stop a running task; a rerun recognises complete "
                f"files): {', '.join(s.left_running)}",
                file=sys.stderr,
            )
        return 130
    finally:
        printer.close()
    return _report(summary, args.output)


def _report(s: RunSummary, out: Path) -> int:
    parts = [f"{s.done} done", f"{s.skipped_done + s.skipped_failed} skipped"]
    if s.skipped_failed:
        parts[-1] += f" ({s.skipped_failed} failed before)"
    parts.append(f"{s.failed} failed")
    rate = ""
    if s.processed and s.seconds > 0:
        rate = f" in {_duration(s.seconds)} ({60 * s.processed / s.seconds:.1f} images/minute)"
    retried = f"; {s.retried} retried after their worker died" if s.retried else ""
    manifest = out / MANIFEST_NAME
    where = f"; manifest {manifest}" if manifest.is_file() else ""
    print(f"torchiid: {', '.join(parts)}{rate}{retried}{where}", file=sys.stderr)
    if s.all_failed:
        print(f"torchiid: {s.all_failed} of {s.total} input(s) failed", file=sys.stderr)
        return 1
    return 0
