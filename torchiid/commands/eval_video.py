"""``torchiid eval video FRAMES RESULTS``: the warping error of a decomposed video.

The temporal consistency of the reflectance in RESULTS (``frame-XXXXXX-*`` files of
``decompose-video``, or ``<frame stem>-*`` of ``decompose``) for every pair of consecutive
frames (:func:`torchiid.eval.video.evaluate_video`); imported by ``torchiid eval`` when it
runs, with its options.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from torchiid._version import __version__
from torchiid.core.exceptions import (
    ImageError,
    ParameterError,
    TorchiidError,
    describe_error,
    one_line,
)
from torchiid.core.progress import progress
from torchiid.eval.results import load_layer
from torchiid.eval.video import VideoPair, evaluate_video, frame_number, occlusion_index
from torchiid.io.layers import OutputError, OutputSet, check_output_folder
from torchiid.video.frames import open_frames
from torchiid.video.write import frame_stem

__all__ = ["run_eval_video"]


def _error_message(where: str, exc: Exception) -> str:
    """One line naming the frame and the problem."""
    msg = describe_error(exc)
    return msg if where in msg else f"{where}: {msg}"


def _load_reflectance(results: Path, index: int, name: str):
    """Frame ``index``'s reflectance from a results folder.

    ``frame-XXXXXX-*`` (the files of ``decompose-video``), else ``<frame file stem>-*``
    (``decompose`` run on the frames).
    """
    try:
        return load_layer(results, frame_stem(index), "reflectance")
    except TorchiidError as first:
        stem = Path(name).stem
        if " frame " in name:  # a video's frame has no file stem
            raise first from None
        try:
            return load_layer(results, stem, "reflectance")
        except TorchiidError:
            raise TorchiidError(
                f"{results}: no reflectance of frame {index + 1} ({name}): neither "
                f"{frame_stem(index)}-* nor {stem}-*"
            ) from None


def run_eval_video(args: argparse.Namespace) -> int:
    """``torchiid eval video FRAMES RESULTS [--flow DIR [--occlusions DIR]]``: exit status."""
    if args.results_dir is None:
        raise ParameterError(
            "eval video needs two folders: the input frames (or video file) and the results "
            "of decompose-video"
        )
    results: Path = args.results_dir
    if not results.is_dir():
        raise TorchiidError(f"{results}: no such results folder")
    if args.flow is not None and not args.flow.is_dir():
        raise TorchiidError(f"{args.flow}: no such flow folder")
    occlusions = None
    if args.occlusions is not None:
        if args.flow is None:
            raise ParameterError("--occlusions marks the pixels of the --flow files: give --flow")
        if not args.occlusions.is_dir():
            raise TorchiidError(f"{args.occlusions}: no such occlusions folder")
        occlusions = occlusion_index(args.occlusions)  # a bad folder stops before any pair
    summary_path = None
    if args.output is not None:
        check_output_folder(args.output)
        summary_path = args.output / "video-summary.json"
        if os.path.lexists(summary_path) and not args.overwrite:
            raise OutputError(f"{summary_path} exists; pass --overwrite to replace it")
    # the options not given keep evaluate_video's defaults (the parser leaves them None)
    taken = inspect.signature(evaluate_video).parameters
    eval_flow = args.eval_flow or taken["method"].default
    space = args.space or taken["space"].default
    source = open_frames(args.dir)
    show = not args.no_progress  # a bar on a terminal, a line now and then in a log
    rows, failures, prev = [], 0, None
    bar = progress(source.count, "frames", "frame", show=show, leave=True)
    try:
        for item in source:
            bar.update(1)
            try:
                if item.error is not None:
                    raise item.error
                refl = _load_reflectance(results, item.index, item.name)
                if tuple(refl.shape[-2:]) != tuple(item.image.shape[-2:]):
                    raise ImageError(
                        f"{results}: the reflectance of frame {item.index + 1} is "
                        f"{refl.shape[-1]}x{refl.shape[-2]}, the frame "
                        f"{item.image.shape[-1]}x{item.image.shape[-2]}"
                    )
                # a folder's frame is numbered by its file name, a video's by its position
                number = item.index + 1
                if source.kind == "folder":
                    number = frame_number(item.name, number)
                current = (item.image, refl, item.name, number)
            except Exception as exc:  # noqa: BLE001 - the other pairs go on
                failures += 1
                bar.write(f"torchiid: error: {_error_message(item.name, exc)}", file=sys.stderr)
                prev = None
                continue
            if prev is not None:
                try:
                    rows += evaluate_video(
                        [prev[0], current[0]],
                        [prev[1], current[1]],
                        [prev[2], current[2]],
                        flow_dir=args.flow,
                        space=space,
                        method=eval_flow,
                        occlusions=occlusions,
                        numbers=[prev[3], current[3]],
                    )
                except TorchiidError as exc:
                    failures += 1
                    bar.write(f"torchiid: error: {one_line(str(exc))}", file=sys.stderr)
            prev = current
    finally:
        source.close()
        bar.close()
    if not rows:
        print("torchiid: error: no pair of consecutive frames could be scored", file=sys.stderr)
        return 1 if failures else 2
    print(_video_table(rows, space, eval_flow, flow=args.flow, occlusions=args.occlusions))
    if summary_path is not None:
        _write_summary(summary_path, rows, args, space=space, eval_flow=eval_flow)
        if not getattr(args, "quiet", False):
            print(f"wrote {summary_path}")
    if failures:
        print(f"torchiid: {failures} frame(s) or pair(s) failed", file=sys.stderr)
        return 1
    return 0


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None and v == v]
    return sum(vals) / len(vals) if vals else None


def _given_flows(rows: Sequence[VideoPair], flow: Path, occlusions: Path | None) -> str:
    """What the 'given' columns used: the ``.flo`` files and where the occlusions came from."""
    given = [r for r in rows if r.given is not None]
    if not given:
        return f"no .flo file in {flow} matched a frame"
    n_maps = sum(r.occlusion_file is not None for r in given)
    folder = occlusions if occlusions is not None else flow
    if n_maps == len(given):
        occluded = f"the occlusion maps in {folder}"
    elif n_maps == 0:
        occluded = "the forward-backward check"
    else:
        occluded = (
            f"the occlusion maps in {folder} ({n_maps} pairs), else the forward-backward check"
        )
    return (
        f"the .flo files in {flow} ({len(given)} of {len(rows)} pairs), occlusions from {occluded}"
    )


def _video_table(
    rows: Sequence[VideoPair],
    space: str,
    eval_flow: str = "dis",
    *,
    flow: Path | None = None,
    occlusions: Path | None = None,
) -> str:
    """The table of the pairs; the 'given' columns only with ``flow`` (the --flow folder)."""

    def cell(v: float | None, digits: int = 5) -> str:
        return f"{'-':>12}" if v is None or v != v else f"{v:>12.{digits}f}"

    columns: list[tuple[str, Callable[[VideoPair], float | None], int]] = [
        ("WE (est.)", lambda r: r.estimated, 5),
        ("input WE", lambda r: r.input_estimated, 5),
        ("valid", lambda r: r.estimated_valid, 3),
    ]
    used = f"est.: {eval_flow} flow estimated on the frames"
    if flow is not None:
        columns += [
            ("WE (given)", lambda r: r.given, 5),
            ("input given", lambda r: r.input_given, 5),
            ("valid given", lambda r: r.given_valid, 3),
        ]
        used += f"; given: {_given_flows(rows, flow, occlusions)}"
    width = max(len("mean"), *(len(f"{r.first} -> {r.second}") for r in rows))
    head = f"{'pair':<{width}}  " + "  ".join(f"{name:>12}" for name, _, _ in columns)
    lines = [
        f"warping error of the reflectance ({space} values in [0, 1]; {used})",
        head,
        "-" * len(head),
    ]
    for r in rows:
        pair = f"{r.first} -> {r.second}"
        cells = "  ".join(cell(get(r), digits) for _, get, digits in columns)
        lines.append(f"{pair:<{width}}  {cells}")
    lines.append("-" * len(head))
    means = "  ".join(cell(_mean(get(r) for r in rows), digits) for _, get, digits in columns)
    lines.append(f"{'mean':<{width}}  {means}")
    return "\n".join(lines)


def _write_summary(
    path: Path, rows: Sequence[VideoPair], args: argparse.Namespace, *, space: str, eval_flow: str
) -> None:
    data = {
        "torchiid_version": __version__,
        "frames": str(args.dir),
        "results": str(args.results_dir),
        "flow": None if args.flow is None else str(args.flow),
        "occlusions": None if args.occlusions is None else str(args.occlusions),
        "eval_flow": eval_flow,
        "space": space,
        "mean": {
            "estimated": _mean(r.estimated for r in rows),
            "input_estimated": _mean(r.input_estimated for r in rows),
            "given": _mean(r.given for r in rows),
            "input_given": _mean(r.input_given for r in rows),
        },
        "pairs": [r.__dict__ for r in rows],
    }
    text = json.dumps(data, indent=2, allow_nan=False, default=str) + "\n"
    with OutputSet(path.parent, overwrite=True, label="video-summary") as tx:
        tx.write(path.name, lambda p: p.write_text(text, encoding="utf-8"))
        tx.commit()
