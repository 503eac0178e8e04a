"""``torchiid decompose-video``: decompose the frames of a video, temporally consistent."""

from __future__ import annotations

import argparse
import json
import logging
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
)
from torchiid.core.progress import progress

if TYPE_CHECKING:
    from torchiid.params import Parameters
    from torchiid.video.temporal import VideoDecomposer, VideoOptions
    from torchiid.video.write import PreviewWriter

__all__ = ["DESCRIPTION", "EPILOG", "add_arguments", "options_from_args", "run"]

log = logging.getLogger("torchiid")

DESCRIPTION = (
    "Decompose a video file (needs PyAV: pip install 'torchiid[video]') or a folder of frames "
    "(sorted by name) frame by frame, each frame tied to the previous one by optical flow: the "
    "warped previous reflectance is the warm start of both stages and the target of a temporal "
    "term, so the reflectance does not flicker."
)

#: ``--flow`` choices and default temporal weights (those of :mod:`torchiid.video`, named
#: here so that ``--help`` needs no torch)
FLOW_METHODS = ("dis", "farneback")
DEFAULT_TEMPORAL_WEIGHT = {"l2": 4.0, "l1": 1.0}

EPILOG = """\
outputs: for frame i (1-based) frame-<i:06d>-reflectance.png, -shading.png, -preview.png,
-reflectance-linear16.png, -shading.exr, -info.json (and the .npy pair with --save-npy), as
`torchiid decompose` writes them; video-params.json (the parameters and video options) and,
with --preview, preview.mp4 ([input | reflectance | shading], H.264). One albedo scale and one
shading_white hold for the whole sequence (set by its first frame).

existing outputs are kept unless --overwrite: a frame whose files all exist is skipped as
done, and its reflectance, read back from frame-*-reflectance-linear16.png, continues the
temporal chain, so the same command again resumes an interrupted run (status 0 when every
frame is written or was done); a frame with only some of its files is reported (status 1). A
rerun whose parameters or video options differ from the folder's video-params.json stops
before any frame (status 2): pass --overwrite or choose another output folder."""


def add_arguments(v: argparse.ArgumentParser) -> None:
    """The options of ``torchiid decompose-video``."""
    v.add_argument("input", type=Path, help="a video file or a folder of frames")
    v.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    add_parameter_options(v)
    v.add_argument(
        "--masks",
        type=Path,
        metavar="DIR",
        help="folder of masks (nonzero = inside), sorted by name: the i-th mask for the i-th "
        "frame; as many masks as frames",
    )
    v.add_argument(
        "--temporal-norm",
        choices=["l2", "l1"],
        default="l2",
        help="the temporal term: l2 (an anchor, default) or l1 (inside Split-Bregman)",
    )
    v.add_argument(
        "--temporal-weight",
        type=finite_float,
        help="weight of the temporal term relative to Stage 2's data term (default: "
        + ", ".join(f"{k} {w:g}" for k, w in DEFAULT_TEMPORAL_WEIGHT.items())
        + "; 0 = none)",
    )
    v.add_argument(
        "--frame-by-frame",
        action="store_true",
        help="no temporal consistency: every frame decomposed on its own, as `decompose` does",
    )
    v.add_argument("--no-warm-start", action="store_true", help="start every frame's solves cold")
    v.add_argument(
        "--no-feature-reuse",
        action="store_true",
        help="compute Stage 0 for every frame (default: reused, warped, while the scene moves "
        "little)",
    )
    v.add_argument(
        "--flow",
        choices=FLOW_METHODS,
        default="dis",
        help="optical flow (OpenCV): dis or farneback",
    )
    v.add_argument(
        "--preview", action="store_true", help="also write preview.mp4 (input | R | S), needs PyAV"
    )
    v.add_argument(
        "--fps", type=finite_float, help="frame rate of the preview (default: the video's, or 24)"
    )
    v.add_argument(
        "--save-npy", action="store_true", help="also write float32 linear .npy arrays per frame"
    )
    add_overwrite_and_linear(v, files="frame")


def options_from_args(args: argparse.Namespace) -> VideoOptions:
    """:class:`~torchiid.video.temporal.VideoOptions` from the command line."""
    from torchiid.core.exceptions import ParameterError
    from torchiid.video.temporal import VideoOptions

    if args.frame_by_frame:
        return VideoOptions.frame_by_frame()
    if args.temporal_weight is not None and not args.temporal_weight >= 0:
        raise ParameterError(f"--temporal-weight must be >= 0, got {args.temporal_weight}")
    return VideoOptions(
        temporal_norm=args.temporal_norm,
        temporal_weight=args.temporal_weight,
        warm_start=not args.no_warm_start,
        reuse_features=not args.no_feature_reuse,
        flow=args.flow,
    )


def _error_message(where: str, exc: Exception) -> str:
    """One line naming the frame and the problem."""
    from torchiid.core.exceptions import describe_error

    msg = describe_error(exc)
    return msg if where in msg else f"{where}: {msg}"


def _params_json(params: Parameters, options: VideoOptions) -> str:
    from torchiid._version import __version__

    data = {
        "torchiid_version": __version__,
        "params": json.loads(params.to_json()),
        "video": {**options.__dict__, "temporal_weight": options.weight},
    }
    return json.dumps(data, indent=2) + "\n"


def _flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(data, dict):
        return {prefix: data}
    flat: dict[str, Any] = {}
    for key, value in data.items():
        flat.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def _check_same_settings(out: Path, params: Parameters, options: VideoOptions) -> None:
    """Refuse to continue a folder decomposed with other settings (its ``video-params.json``).

    Resuming chains the new frames to the frames already written; with other parameters or
    video options the sequence would silently mix two settings.

    Raises:
        TorchiidError: ``video-params.json`` differs or cannot be read.
    """
    from torchiid.core.exceptions import TorchiidError
    from torchiid.video.write import PARAMS_NAME

    path = out / PARAMS_NAME
    if not os.path.lexists(path):
        return
    hint = "pass --overwrite to replace the outputs or choose another output folder"
    try:
        old = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise TorchiidError(
            f"{path}: cannot read the earlier run's settings ({exc}); {hint}"
        ) from None
    new = json.loads(_params_json(params, options))
    a, b = _flatten(old), _flatten(new)
    # the version that wrote the files is no setting: an upgrade may resume the sequence
    keys = {k for k in a.keys() | b.keys() if not k.endswith("torchiid_version")}
    changed = sorted(k for k in keys if a.get(k, None) != b.get(k, None))
    if changed:
        shown = ", ".join(f"{k} {a.get(k)!r} -> {b.get(k)!r}" for k in changed[:3])
        more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        raise TorchiidError(
            f"{path}: the outputs there were made with other settings ({shown}{more}); {hint}"
        )


def _resume(video: VideoDecomposer, out: Path, stem: str, image, mask) -> bool:
    """Continue the chain from a frame written earlier; False when its files cannot be read."""
    from torchiid.core.exceptions import TorchiidError
    from torchiid.io import load_image

    try:
        refl = load_image(out / f"{stem}-reflectance-linear16.png", linear=True, min_side=1)
        white = json.loads((out / f"{stem}-info.json").read_text(encoding="utf-8"))
        white = float(white["shading_white"])
        if refl.image.shape != image.shape:
            return False
        video.remember(image, refl.image, mask, shading_white=white)
        return True
    except (TorchiidError, OSError, ValueError, KeyError, TypeError):
        return False


def run(args: argparse.Namespace) -> int:
    """Run ``torchiid decompose-video``; returns the exit status (see the command's help)."""
    from tqdm import tqdm

    from torchiid.core.device import resolve_device
    from torchiid.core.exceptions import ImageError, ParameterError, TorchiidError, one_line
    from torchiid.io import load_mask
    from torchiid.io.layers import OutputError, OutputSet, check_output_folder
    from torchiid.pipeline.results import solve_record
    from torchiid.video.frames import list_images, open_frames
    from torchiid.video.temporal import VideoDecomposer
    from torchiid.video.write import (
        PARAMS_NAME,
        PREVIEW_NAME,
        PreviewWriter,
        frame_file_names,
        frame_stem,
        write_frame,
    )

    params = params_from_args(args)
    options = options_from_args(args)
    if args.fps is not None and not args.fps > 0:
        raise ParameterError(f"--fps must be > 0, got {args.fps}")
    device = resolve_device(args.device)
    out: Path = args.output
    check_output_folder(out)
    if not args.overwrite:
        _check_same_settings(out, params, options)
    source = open_frames(args.input, linear=args.linear)
    masks = None
    if args.masks is not None:
        if not args.masks.is_dir():
            raise TorchiidError(f"{args.masks}: --masks must be a folder of mask images")
        masks = list_images(args.masks)
        if source.count is not None and len(masks) != source.count:
            raise TorchiidError(
                f"{args.masks}: holds {len(masks)} masks but {args.input} has {source.count} "
                "frames; give one mask per frame"
            )
    show = not args.no_progress  # a bar on a terminal, a line now and then in a log

    def tell(message: str) -> None:  # a line; above the progress bar while it shows
        tqdm.write(message, file=sys.stderr)

    failures = written = seen = skipped = 0
    preview = None
    kept_preview = None  # an earlier run's preview, kept: stale if this run writes a frame
    if args.preview:
        target = out / PREVIEW_NAME
        if os.path.lexists(target) and not args.overwrite:
            kept_preview = target
        else:
            preview = PreviewWriter(target, args.fps or source.fps or 24.0, overwrite=True)
    video = VideoDecomposer(params, options)
    params_written = False
    bar = progress(source.count, "frames", "frame", show=show)
    tx: OutputSet | None = None
    where = str(args.input)
    try:
        for item in source:
            seen += 1
            where = f"{source.path / item.name}" if source.kind == "folder" else item.name
            bar.update(1)
            stem = frame_stem(item.index)
            try:
                if item.error is not None:
                    raise item.error
                image, mask = item.image, item.mask
                if masks is not None:
                    if item.index >= len(masks):
                        raise ImageError(f"{args.masks}: no mask for frame {item.index + 1}")
                    m = load_mask(masks[item.index], shape=tuple(image.shape[-2:]))
                    mask = m if mask is None else (mask & m)
                names = frame_file_names(stem, save_npy=args.save_npy)
                existing = [out / n for n in names if os.path.lexists(out / n)]
                for target in existing:
                    if target.is_dir() and not target.is_symlink():
                        raise OutputError(f"{target}: is a folder; cannot replace it by an output")
                if existing and not args.overwrite:
                    resumed = _resume(video, out, stem, image, mask)
                    if not resumed:
                        video.reset()
                    elif preview is not None:
                        _preview_from_files(preview, out, stem, image)
                    if resumed and len(existing) == len(names):  # done by an earlier run
                        skipped += 1
                        log.info("%s: %s/%s-* exist; skipped", where, out, stem)
                        continue
                    if resumed:  # e.g. written without the --save-npy files asked for now
                        missing = [n for n in names if not os.path.lexists(out / n)]
                        raise OutputError(
                            f"{out / stem}-*: written earlier without {', '.join(missing)}; "
                            "pass --overwrite to write the frame again"
                        )
                    raise OutputError(f"{existing[0]} exists; pass --overwrite to replace it")
                t0 = time.perf_counter()
                frame = _decompose_frame(
                    video, image.to(device), None if mask is None else mask.to(device)
                )
                seconds = time.perf_counter() - t0
                d = frame.decomposition
                _solver_lines(args, where, d, stem, tell)
                white = float(d.shading_white[0])
                info = {
                    "input": str(args.input),
                    "frame": item.index + 1,
                    "frame_name": item.name,
                    "working_size": list(reversed(d.working_size)),
                    "linked_to_previous": frame.linked,
                    "trusted_share": round(frame.trusted, 4),
                    "motion_px": round(frame.motion, 3),
                    "features_reused": frame.features_reused,
                    "scale": frame.scale,
                    **solve_record(d, params, seconds, frame.times, places=4),
                    "parameters": PARAMS_NAME,
                }
                refl = d.reflectance[0].cpu()
                shading = d.shading[0].cpu()
                msk = None if d.mask is None else d.mask[0].cpu()
                tx = OutputSet(out, overwrite=args.overwrite, label=stem)
                with tx:
                    write_frame(
                        tx, stem, image, refl, shading, shading_white=white, info=info,
                        mask=msk, save_npy=args.save_npy,
                    )  # fmt: skip
                    tx.commit()
                written, tx = written + 1, None
                if not params_written:  # with the first frame: a run that fails writes nothing
                    params_written = _write_params(out, params, options, args.overwrite)
                if preview is not None:
                    preview.add(image, refl, shading / white)
                done = f"{where} -> {out}/{stem}-* ({seconds:.1f} s)"
                if show:
                    tqdm.write(done, file=sys.stderr)
                else:
                    log.info(done)
            except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the video
                failures, tx = failures + 1, None
                tell(f"torchiid: error: {_error_message(where, exc)}")
                if not isinstance(exc, TorchiidError):
                    log.info("the error above came from here:", exc_info=exc)
        if preview is not None:
            try:
                preview.commit()
            except TorchiidError as exc:
                failures += 1
                tell(f"torchiid: error: {one_line(str(exc))}")
    except KeyboardInterrupt:
        bar.close()
        if preview is not None:
            preview.discard()
        if tx is not None and tx.committed:
            written += 1
        print(
            f"torchiid: interrupted; {written} frame(s) written"
            + (" (the preview was not)" if preview is not None else ""),
            file=sys.stderr,
        )
        return 130
    except TorchiidError as exc:  # the video stream itself broke: nothing more to read
        bar.close()
        failures += 1
        tell(f"torchiid: error: {one_line(str(exc))}")
        if preview is not None:
            preview.discard()
    finally:
        source.close()
    bar.close()
    if seen == 0:
        raise TorchiidError(f"{args.input}: holds no frames")
    if kept_preview is not None and written:
        failures += 1
        tell(
            f"torchiid: error: {kept_preview} exists and lacks the frames written now; pass "
            "--overwrite to replace it"
        )
    if skipped and not getattr(args, "quiet", False):
        print(
            f"torchiid: {written} frame(s) written, {skipped} skipped (written by an earlier "
            "run; --overwrite replaces them)",
            file=sys.stderr,
        )
    if failures:
        print(f"torchiid: {failures} of {seen} frame(s) failed", file=sys.stderr)
        return 1
    return 0


def _decompose_frame(video: VideoDecomposer, image: Any, mask: Any) -> Any:
    """One frame; a capped solve is reported by :func:`_solver_lines`, not as a warning."""
    from torchiid.core.exceptions import ConvergenceWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return video(image, mask)


def _solver_lines(args: argparse.Namespace, where: str, d: Any, stem: str, tell) -> None:
    """The frame's note on solves that stopped early (``-v``: also the preset's caps)."""
    from torchiid.collection.job import solver_note

    note, detail = solver_note(where, list(d.solves), d.params.converge, f"{stem}-info.json")
    if note and not getattr(args, "quiet", False):
        tell(f"torchiid: note: {note}")
    if detail and getattr(args, "verbose", False):
        tell(f"torchiid: {detail}")


def _write_params(out: Path, params: Parameters, options: VideoOptions, overwrite: bool) -> bool:
    """Write ``video-params.json``; an existing one is kept without ``overwrite``.

    (It holds the same settings: :func:`_check_same_settings` stopped the run otherwise.)
    """
    from torchiid.io.layers import OutputSet
    from torchiid.video.write import PARAMS_NAME

    target = out / PARAMS_NAME
    if os.path.lexists(target) and not overwrite:
        return True
    with OutputSet(out, overwrite=True, label="video-params") as tx:
        text = _params_json(params, options)
        tx.write(PARAMS_NAME, lambda p: p.write_text(text, encoding="utf-8"))
        tx.commit()
    return True


def _preview_from_files(preview: PreviewWriter, out: Path, stem: str, image) -> None:
    """Add a frame written by an earlier run to the preview, from its 8-bit files."""
    from torchiid.io import load_image

    refl = load_image(out / f"{stem}-reflectance.png", min_side=1).image
    shading = load_image(out / f"{stem}-shading.png", min_side=1).image[:1]
    preview.add(image, refl, shading)
