"""``torchiid eval``: score a method (or a folder of results) on an evaluation dataset.

The command line of :class:`torchiid.eval.EvalRunner`: this module parses the options,
runs the evaluation and prints the per-image and mean table. The metrics per dataset are
described in :mod:`torchiid.eval.scoring`, the output files (``results.csv``,
``summary.json``), resuming and batching in :mod:`torchiid.eval.runner`.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from torchiid.commands.common import (
    add_parameter_options,
    finite_float,
    params_from_args,
    say,
)

__all__ = ["DATASETS", "DESCRIPTION", "EPILOG", "METHODS", "add_arguments", "run"]

#: the benchmark layouts and methods (:data:`torchiid.eval.datasets.DATASETS`,
#: :data:`torchiid.eval.methods.METHODS`, named here so that ``--help`` needs no torch)
DATASETS = ("iiw", "mit", "saw", "dense")
METHODS = ("semantic", "retinex", "r=i", "s=i")

DESCRIPTION = (
    "Decompose every image of an evaluation dataset (or read an existing results folder) and "
    "score it: WHDR (iiw), LMSE (mit), shading AP (saw), si-MSE / LMSE / DSSIM (dense). Prints "
    "a per-image and mean table and writes results.csv and summary.json."
)

EPILOG = """\
results folder (--results DIR): instead of running a method, read the layers of every
dataset id from DIR, the exact files first: <id>-reflectance.npy and <id>-shading.npy
(float32 linear, `torchiid decompose --save-npy`), else <id>-reflectance-linear16.png and
<id>-shading.exr (16-bit linear and float OpenEXR, written by `torchiid decompose`), else
<id>-reflectance.png and <id>-shading.png (8-bit sRGB, decoded to linear). The id is the
IIW/SAW photo id, the MIT object name, or the dense image name; the layers must have the
image's size. MIT-Berkeley's PNGs are 16-bit linear: decompose them with --linear and
each object's mask, from flat <object>.png copies (docs/guide/evaluation.md).

resuming: results.csv gets a row as each image finishes. With --resume (the default) the
ids already in it are skipped and counted in the summary; the run's settings must match
those in summary.json, and its --ids / --limit must select every id in results.csv (a run
may go on to more images, not to others). --no-resume refuses to touch an existing
results.csv; --overwrite discards it and starts over. Failed images get no row, so a
resumed run retries them.

options that do not apply (--delta outside iiw, --input outside mit, the video options
outside video, the parameter options with a baseline or --results) are named in a note
and ignored.

batching: images of equal size are decomposed together in batches of --batch-size (at
most 4 x batch-size images wait in memory for a partner of their size).

seconds (results.csv): the method's wall time per image (a batch's time divided by its
size; dataset reading and scoring excluded); with --results, the time to read and score.

video (torchiid eval video FRAMES RESULTS [--flow DIR]): the warping error of Lai et al.
(2018) of the reflectance in RESULTS (frame-XXXXXX-* files of decompose-video, or
<frame stem>-* of decompose) for every pair of consecutive frames: flow estimated on the
frames (OpenCV DIS), non-occluded pixels by a forward-backward check, and with --flow the
given flows (their columns only then); with -o, OUT/video-summary.json."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``torchiid eval``."""
    p.add_argument("dataset", choices=[*DATASETS, "video"], help="which benchmark layout DIR has")
    p.add_argument("dir", type=Path, metavar="DIR", help="the dataset directory")
    p.add_argument(
        "results_dir",
        type=Path,
        nargs="?",
        metavar="RESULTS_DIR",
        help="(video only) the decompose-video output folder to score; DIR holds the input "
        "frames (or is the video file)",
    )
    p.add_argument(
        "-o", "--output", type=Path, help="output folder (default: ./eval-<dataset>-<method>)"
    )
    p.add_argument(
        "--method",
        choices=METHODS,
        help="semantic: the paper's method (default); retinex: colour Retinex; "
        "r=i: reflectance = image, shading = 1; s=i: shading = gray image, "
        "reflectance = 1 (reference rows)",
    )
    add_parameter_options(p)
    p.add_argument(
        "--batch-size",
        type=int,
        help="images of equal size decomposed together (default 1)",
    )
    p.add_argument("--limit", type=int, help="evaluate only the first N images of the set")
    p.add_argument(
        "--ids", type=Path, help="file of ids to evaluate, one a line (e.g. an IIW/SAW test split)"
    )
    p.add_argument(
        "--input",
        choices=["diffuse", "original"],
        help="MIT input image (default diffuse, the standard protocol)",
    )
    p.add_argument(
        "--results",
        type=Path,
        metavar="DIR",
        help="score the decompositions in DIR instead of running --method (see below)",
    )
    p.add_argument(
        "--resume",
        action=argparse.BooleanOptionalAction,
        help="skip the ids already in OUT/results.csv (default: on)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="discard existing results in the output folder and start over",
    )
    p.add_argument("--delta", type=finite_float, help="WHDR equality margin (iiw; default 0.10)")
    p.add_argument(
        "--flow",
        type=Path,
        metavar="DIR",
        help="(video) ground-truth flows: <frame stem>.flo (Middlebury) from each frame to the "
        "next; occlusions from --occlusions, else <stem>-occlusions.png or occlusions_NNNN.png "
        "in DIR (the shared sintel-clean sample's layout), else the forward-backward check",
    )
    p.add_argument(
        "--occlusions",
        type=Path,
        metavar="DIR",
        help="(video, with --flow) occlusion maps of the ground-truth flows: PNGs, white = "
        "occluded, matched to the flow's first frame by the number ending the file name "
        "(MPI Sintel's occlusions/<scene>/frame_0002.png: frame 2's pixels hidden in frame 3)",
    )
    p.add_argument(
        "--eval-flow",
        choices=["dis", "farneback"],
        help="(video) optical flow estimated on the frames for the 'estimated' columns "
        "(default dis; farneback scores a DIS-based result with a flow it did not follow)",
    )
    p.add_argument(
        "--space",
        choices=["srgb", "linear"],
        help="(video) values the warping error compares: sRGB (default, as Lai et al.) or "
        "linear, both in [0, 1]",
    )


# --------------------------------------------------------------------------- table


def _table(
    ids: list[str],
    rows: dict[str, dict[str, float]],
    columns: list[str],
    means: dict[str, float | None],
) -> str:
    from torchiid.eval.scoring import COUNT_COLUMNS

    width = max([len("mean"), len("id"), *(len(i) for i in ids)])
    cols = columns[1:]
    widths = [max(len(c), 10) for c in cols]
    head = f"{'id':<{width}}  " + "  ".join(f"{c:>{w}}" for c, w in zip(cols, widths, strict=True))

    def cell(c: str, v: float | None, w: int) -> str:
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return f"{'-':>{w}}"
        return f"{int(v):>{w}d}" if c in COUNT_COLUMNS else f"{v:>{w}.4f}"

    lines = [head, "-" * len(head)]
    for i in ids:
        r = rows[i]
        lines.append(
            f"{i:<{width}}  "
            + "  ".join(cell(c, r[c], w) for c, w in zip(cols, widths, strict=True))
        )
    lines.append("-" * len(head))
    lines.append(
        f"{'mean':<{width}}  "
        + "  ".join(cell(c, means.get(c), w) for c, w in zip(cols, widths, strict=True))
    )
    return "\n".join(lines)


# --------------------------------------------------------------------------- run


def _report_failure(sample_id: str, exc: Exception) -> None:
    from tqdm import tqdm

    tqdm.write(f"torchiid: error: {sample_id}: {exc}", file=sys.stderr)


#: the parameter options of ``--method semantic`` (:func:`add_parameter_options`)
_PARAMETER_OPTIONS = ("params", "variant", "iterations", "max_side")
#: the options of ``eval video`` alone
_VIDEO_OPTIONS = ("flow", "occlusions", "eval_flow", "space")
#: the options ``eval video`` does not use
_NOT_VIDEO_OPTIONS = ("method", "batch_size", "limit", "ids", "input", "results", "delta")


def _flag(name: str) -> str:
    return f"--{name.replace('_', '-')}"


def _given(args: argparse.Namespace, names: tuple[str, ...]) -> list[str]:
    """The options of ``names`` given on the command line (their defaults are ``None``)."""
    return [_flag(n) for n in names if getattr(args, n, None) is not None]


def _unused_options(args: argparse.Namespace) -> list[str]:
    """The options given that the run ignores, grouped by why: ``"--delta (iiw only)"``."""
    groups: list[str] = []

    def add(names: list[str], why: str) -> None:
        if names:
            groups.append(f"{', '.join(names)} ({why})")

    parameters = (["--preset"] if args.preset != "default" else []) + _given(
        args, _PARAMETER_OPTIONS
    )
    if args.dataset == "video":
        no_resume = ["--no-resume"] if args.resume is False else []
        add(
            _given(args, _NOT_VIDEO_OPTIONS) + no_resume + parameters,
            "eval video scores the reflectance in RESULTS_DIR",
        )
        return groups
    add(_given(args, _VIDEO_OPTIONS), "eval video only")
    if args.dataset != "iiw":
        add(_given(args, ("delta",)), "iiw only")
    if args.dataset != "mit":
        add(_given(args, ("input",)), "mit only")
    if args.results is not None:
        add(
            _given(args, ("method", "batch_size")) + parameters,
            "--results scores the layers in its folder as they are",
        )
    elif args.method not in (None, "semantic"):
        add(parameters, "--method semantic only")
    return groups


def _note_unused(args: argparse.Namespace) -> None:
    """One note naming the options given that the run ignores (none with ``-q``)."""
    groups = _unused_options(args)
    if groups:
        say(args, f"torchiid: note: not used by eval {args.dataset}: {'; '.join(groups)}")


def run(args: argparse.Namespace) -> int:
    """Run ``torchiid eval``; returns the exit status (1 if any image failed)."""
    from torchiid.core.exceptions import ParameterError
    from torchiid.eval.options import EvalOptions, check_ranges
    from torchiid.eval.runner import EvalRunner

    if args.dataset == "video":
        from torchiid.commands.eval_video import run_eval_video

        _note_unused(args)
        return run_eval_video(args)
    if args.results_dir is not None:
        raise ParameterError(f"eval {args.dataset} takes one folder, got {args.results_dir} too")
    _note_unused(args)
    # the options not given keep EvalOptions' defaults (the parser leaves them None, so that
    # the note above can tell what was typed)
    given = {
        name: value
        for name, value in (
            ("method", args.method),
            ("batch_size", args.batch_size),
            ("input", args.input),
            ("delta", args.delta),
            ("resume", args.resume),
        )
        if value is not None
    }
    defaults = EvalOptions()
    check_ranges(
        given.get("batch_size", defaults.batch_size),
        args.limit,
        given.get("delta", defaults.delta),
        flags=True,
    )
    semantic = given.get("method", defaults.method) == "semantic"
    params = params_from_args(args) if args.results is None and semantic else None
    options = EvalOptions(
        params=params,
        output=args.output,
        results_dir=args.results,
        device=args.device,
        limit=args.limit,
        ids=args.ids,
        overwrite=args.overwrite,
        progress=not args.no_progress,  # a bar on a terminal, a line now and then in a log
        on_failure=_report_failure,
        **given,
    )
    result = EvalRunner(args.dataset, args.dir, options).run()
    for note in result.notes:
        say(args, f"torchiid: note: {note}")
    data = result.summary
    print(_table(list(result.rows), result.rows, list(result.columns), data["mean"]))
    if args.dataset == "saw":
        ap = data["pooled_ap"]
        print(
            f"pooled AP over {data['pooled_ap_images']} images: "
            + ("-" if ap is None else f"{ap:.4f}")
        )
    if data["median_seconds"] is not None:
        print(f"median seconds per image: {data['median_seconds']:.3f}")
    if not getattr(args, "quiet", False):
        print(f"wrote {result.csv_path} and {result.summary_path}")
    if result.failures:
        print(
            f"torchiid: {len(result.failures)} of {len(result.ids)} image(s) failed",
            file=sys.stderr,
        )
        return 1
    return 0
