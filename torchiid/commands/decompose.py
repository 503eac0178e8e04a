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
from typing import TYPE_CHECKING

from torchiid.commands.common import add_parameter_options, params_from_args, progress_bars, say

if TYPE_CHECKING:
    from torchiid.collection import ImageResult, Plan, Progress, RunSettings, RunSummary
    from torchiid.params import Parameters

__all__ = ["DESCRIPTION", "add_arguments", "run"]

log = logging.getLogger("torchiid")

DESCRIPTION = """\
Split photos into reflectance and shading. For photo.jpg it writes into the output folder
photo-reflectance.png and photo-shading.png (8-bit sRGB, viewable), photo-preview.png,
photo-reflectance-linear16.png and photo-shading.exr (the exact layers, linear),
photo-sigma.exr (the Stage 1 shading, for `torchiid edit --from`), photo-info.json and
photo-params.json; and manifest.jsonl, which makes a rerun skip what is done."""


#: the options that are :class:`~torchiid.collection.RunSettings` fields of the same name
_SETTINGS_OPTIONS = (
    "method",
    "linear",
    "device",
    "overwrite",
    "save_npy",
    "save_confidence",
    "save_stage1",
    "save_iterations",
    "mask",
    "threads",
    "redo",
)

#: the switches that write more files, in the order ``--help`` lists them
_SAVE_OPTIONS = {
    "--save-confidence": "also write <stem>-confidence.png (255: trusted colour, 0: dark or "
    "clipped pixel, in between on the ramps near them)",
    "--save-stage1": "also write the last Stage 1 reflectance <stem>-rho.exr (float, linear; "
    "`torchiid edit --from` rebuilds it from the photo and <stem>-sigma.exr otherwise)",
    "--save-npy": "also write float32 linear .npy arrays of reflectance and shading",
    "--save-iterations": "write every iteration's sigma, rho, R, S (sRGB PNGs)",
}


def add_arguments(d: argparse.ArgumentParser) -> None:
    """The options of ``torchiid decompose``."""
    d.add_argument(
        "inputs",
        nargs="*",
        help="image files, directories and glob patterns (quote them: 'photos/**/*.jpg')",
    )
    d.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    d.add_argument("-r", "--recursive", action="store_true", help="also take images in subfolders")
    d.add_argument(
        "--list",
        action="append",
        type=Path,
        metavar="FILE",
        help="a list of inputs: one path per line, or a CSV file with a 'path' and an optional "
        "'mask' column; relative paths are relative to the list's folder (repeatable)",
    )
    d.add_argument(
        "--method",
        default="semantic",
        choices=["semantic", "retinex"],
        help="semantic: the paper's method (default); retinex: Grosse et al.'s "
        "colour Retinex baseline",
    )
    add_parameter_options(d)
    d.add_argument(
        "--mask", type=Path, help="mask image (nonzero = inside); applies to every input"
    )
    d.add_argument(
        "--linear",
        action="store_true",
        help="8/16-bit input files hold linear values (default: sRGB-encoded)",
    )
    for option, text in _SAVE_OPTIONS.items():
        d.add_argument(option, action="store_true", help=text)
    d.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    d.add_argument(
        "--retry-failed",
        action="store_true",
        help="also run the inputs the manifest records as failed (skipped otherwise)",
    )
    d.add_argument(
        "--redo",
        action="store_true",
        help="ignore the manifest: run every input again (with --overwrite to replace files)",
    )
    d.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run N worker processes on this machine, each with its share of the cores "
        "(--threads: each worker's, default cores / N; default: one image at a time in this "
        "process)",
    )
    d.add_argument(
        "--dask-scheduler",
        metavar="ADDRESS",
        help="send the images to the dask.distributed cluster of this scheduler "
        "(e.g. tcp://10.0.0.1:8786); needs pip install 'torchiid[dask]'",
    )
    d.add_argument(
        "--retries",
        type=int,
        default=1,
        metavar="N",
        help="times an image is tried again when its worker dies (--workers) or its task "
        "raises (Dask retries=); default 1",
    )


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
        self.show = progress_bars(args)
        # without a bar because stderr is a log or a pipe: a line per image instead
        self.lines = not self.show and not args.no_progress
        self.quiet = getattr(args, "quiet", False)
        self.verbose = getattr(args, "verbose", False)
        self.out = out
        self.bar = None

    def note(self, message: str) -> None:
        """A note (``torchiid: note: ...``) or a summary line: not with ``-q``."""
        if not self.quiet:
            self.say(message)

    def say(self, message: str) -> None:
        """Any line, above the progress bar while it shows."""
        if self.bar is not None:
            from tqdm import tqdm

            tqdm.write(message, file=sys.stderr)  # above the progress bar, not into its line
        else:
            print(message, file=sys.stderr)

    def planned(self, plan: Plan, summary: RunSummary) -> None:
        from tqdm import tqdm

        for item, record in plan.failed_before:
            self.note(
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
        for note in (result.note or "").splitlines():
            self.note(f"torchiid: note: {note}")
        if result.detail and self.verbose:
            self.say(f"torchiid: {result.detail}")
        how = "complete files found" if result.recovered else f"{result.seconds:.1f} s"
        line = f"{result.path} -> {self.out}/{result.key}-* ({how})"
        if progress.to_process > 1:
            eta = progress.eta
            line += (
                f"; {progress.processed} of {progress.to_process}, "
                f"{progress.per_minute:.1f} images/minute"
                + (f", {_duration(eta)} left" if eta is not None and eta > 0 else "")
            )
        if self.bar is not None or self.lines:
            self.note(line)
        else:
            log.info(line)

    def retrying(self, job, how: str) -> None:
        self.note(f"torchiid: note: {job.path}: its worker process died ({how}); trying it again")

    def compiling(self) -> None:
        from torchiid.core.first_compile import COMPILING

        self.note(f"torchiid: note: {COMPILING}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _settings(args: argparse.Namespace, params: Parameters, out: Path) -> RunSettings:
    from torchiid.collection import RunSettings, file_sha256

    mask_sha = None
    if args.mask is not None:
        from torchiid.io import load_mask

        load_mask(args.mask)  # a missing, unreadable or empty mask is a set-up error
        mask_sha = file_sha256(args.mask)
    # an option a caller's namespace lacks keeps the field's default
    given = {name: getattr(args, name) for name in _SETTINGS_OPTIONS if hasattr(args, name)}
    return RunSettings(out=out, params=params, mask_sha256=mask_sha, **given)


def run(args: argparse.Namespace) -> int:
    """Run ``torchiid decompose``; returns the exit status.

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
    from torchiid.collection import RunInterrupted, run_collection
    from torchiid.collection.manifest import MANIFEST_NAME, Manifest
    from torchiid.core.exceptions import TorchiidError
    from torchiid.io.inputs import list_inputs, unique_keys, walks_into
    from torchiid.io.output_set import check_output_folder

    params = params_from_args(args)
    if args.device not in ("auto", "cpu"):  # a device asked for by name is checked now
        from torchiid.core.device import resolve_device

        resolve_device(args.device)
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
    written: set[str] = set()  # what a run wrote into an input folder is not an input
    if walks_into(args.inputs, out):
        try:
            written = Manifest(out / MANIFEST_NAME).written_files(out)
        except OSError:  # an unreadable manifest: the run says why, before any image
            pass
    items = unique_keys(
        list_inputs(
            args.inputs,
            recursive=getattr(args, "recursive", False),
            lists=lists,
            exclude=[out],
            skip=written,
        )
    )
    settings = _settings(args, params, out)
    if scheduler is not None:  # the workers may run in another folder, or elsewhere
        absolute = {"out": Path(os.path.abspath(out))}
        if args.mask is not None:
            absolute["mask"] = Path(os.path.abspath(args.mask))
        settings = dataclasses.replace(settings, **absolute)
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
            show_progress=printer.show,
            reporter=printer,
            release_models=True,  # the command ends with the run
        )
    except RunInterrupted as stop:
        printer.close()
        s = stop.summary
        where = ""
        if s.interrupted_on:
            names = ", ".join(s.interrupted_on)
            them = "it" if len(s.interrupted_on) == 1 else "them"
            where = f" while processing {names} (nothing of {them} was written)"
        skipped = f", {s.skipped_done} skipped as done before" if s.skipped_done else ""
        print(
            f"torchiid: interrupted{where}; {s.done} of {s.total} input(s) written{skipped}",
            file=sys.stderr,
        )
        if s.left_running:  # files may still appear: said even with -q
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
    return _report(summary, args)


def _report(s: RunSummary, args: argparse.Namespace) -> int:
    from torchiid.collection import MANIFEST_NAME

    parts = [f"{s.done} done", f"{s.skipped_done + s.skipped_failed} skipped"]
    if s.skipped_failed:
        parts[-1] += f" ({s.skipped_failed} failed before)"
    parts.append(f"{s.failed} failed")
    rate = ""
    if s.processed and s.seconds > 0:
        # the rate of the decompositions: failures end early and would inflate it
        per_minute = f" ({60 * s.done / s.seconds:.1f} images/minute)" if s.done else ""
        rate = f" in {_duration(s.seconds)}{per_minute}"
    retried = f"; {s.retried} retried after their worker died" if s.retried else ""
    manifest = args.output / MANIFEST_NAME
    where = f"; manifest {manifest}" if manifest.is_file() else ""
    say(args, f"torchiid: {', '.join(parts)}{rate}{retried}{where}")
    if s.all_failed:
        print(f"torchiid: {s.all_failed} of {s.total} input(s) failed", file=sys.stderr)
        return 1
    return 0
