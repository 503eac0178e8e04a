"""The ``torchiid`` command line: a thin layer over the library.

Subcommands: ``decompose`` (the method, or colour Retinex), ``decompose-video`` (frame
sequences, temporally consistent), ``features`` (look at the Stage 0
features), ``export-onnx`` (write the ONNX backbone) and ``eval`` (metrics on datasets).
Errors a user can cause end in a one-line ``torchiid: error: ...`` and a non-zero exit status:
0 when everything was done, 1 when some inputs failed (the others were done), 2 for a usage or
set-up error (nothing was processed) and 130 when interrupted (Ctrl-C, SIGINT or SIGTERM).
An unexpected exception is reported in one line too; ``--verbose`` adds its traceback.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from torchiid.commands.decompose import add_parameter_options
from torchiid.core.exceptions import TorchiidError, caused_by_interrupt, one_line

__all__ = ["main", "build_parser"]

log = logging.getLogger("torchiid")


def _add_common_image_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--linear",
        action="store_true",
        help="8/16-bit input files hold linear values (default: sRGB-encoded)",
    )
    p.add_argument(
        "--device",
        default="auto",
        choices=["auto", "cpu", "cuda"],
        help="where to run (auto: CUDA when available)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``torchiid`` command."""
    parser = argparse.ArgumentParser(
        prog="torchiid",
        description="Intrinsic image decomposition (I = R x S) with semantic hierarchical priors.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log details to stderr")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    d = sub.add_parser(
        "decompose",
        help="split photos into reflectance and shading",
        description="Split photos into reflectance and shading.",
    )
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
        "--save-confidence",
        action="store_true",
        help="also write <stem>-confidence.png (255: trusted colour, 0: dark or clipped pixel)",
    )
    d.add_argument(
        "--save-stage1",
        action="store_true",
        help="also write the last Stage 1 layers <stem>-sigma.exr and <stem>-rho.exr (float, "
        "linear), which `torchiid edit --from` needs for merge and the illumination edits",
    )
    d.add_argument(
        "--save-npy",
        action="store_true",
        help="also write float32 linear .npy arrays of reflectance and shading",
    )
    d.add_argument(
        "--save-iterations",
        action="store_true",
        help="write every iteration's sigma, rho, R, S (sRGB PNGs)",
    )
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
        "(default: one image at a time in this process)",
    )
    d.add_argument(
        "--threads",
        type=int,
        metavar="T",
        help="torch threads per worker (default with --workers: cores / N)",
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
    d.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_common_image_options(d)

    f = sub.add_parser(
        "features",
        help="write pictures of the Stage 0 semantic features",
        description="Write the PCA image of g_i, proposal masks and the patch "
        "grid of one photo, and print timings per step.",
    )
    f.add_argument("input", type=Path, help="an image file")
    f.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    f.add_argument(
        "--mode", default="shared", choices=["shared", "crop"], help="patch feature mode"
    )
    f.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    _add_common_image_options(f)

    e = sub.add_parser(
        "export-onnx",
        help="export the EfficientNet-Lite0 feature extractor",
        description="Export the CNN feature extractor to ONNX and record its "
        "SHA-256 in the manifest.",
    )
    e.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="where to write (default: the cache used by the library)",
    )

    from torchiid.commands.video import add_video_parser

    add_video_parser(sub)
    from torchiid.commands.eval import add_eval_parser

    add_eval_parser(sub)
    from torchiid.commands.edit import add_edit_parser

    add_edit_parser(sub)
    from torchiid.commands.app import add_parser as add_app_parser

    add_app_parser(sub)
    return parser


def _cmd_decompose(args: argparse.Namespace) -> int:
    from torchiid.commands.decompose import run_decompose

    return run_decompose(args)


def _cmd_features(args: argparse.Namespace) -> int:
    from torchiid.commands.features import run_features

    return run_features(args)


def _cmd_export(args: argparse.Namespace) -> int:
    from torchiid.features.onnx_backend import ensure_onnx_model, export_to_dir

    t0 = time.perf_counter()
    path = export_to_dir(args.output) if args.output else ensure_onnx_model()
    print(f"wrote {path} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _cmd_decompose_video(args: argparse.Namespace) -> int:
    from torchiid.commands.video import run_decompose_video

    return run_decompose_video(args)


def _cmd_eval(args: argparse.Namespace) -> int:
    from torchiid.commands.eval import run_eval

    return run_eval(args)


def _cmd_edit(args: argparse.Namespace) -> int:
    from torchiid.commands.edit import run_edit

    return run_edit(args)


def _cmd_app(args: argparse.Namespace) -> int:
    from torchiid.commands.app import run

    return run(args)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchiid`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="torchiid: %(message)s"
    )
    handlers = {
        "decompose": _cmd_decompose,
        "decompose-video": _cmd_decompose_video,
        "features": _cmd_features,
        "export-onnx": _cmd_export,
        "eval": _cmd_eval,
        "edit": _cmd_edit,
        "app": _cmd_app,
    }
    main_thread = threading.current_thread() is threading.main_thread()
    if main_thread:
        # SIGTERM (kill, timeout, a closed session) cleans up like Ctrl-C
        previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        return handlers[args.command](args)
    except TorchiidError as exc:
        print(f"torchiid: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("torchiid: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - a one-line report, the traceback with -v
        if caused_by_interrupt(exc):  # Ctrl-C inside a compiled kernel
            print("torchiid: interrupted", file=sys.stderr)
            return 130
        print(
            f"torchiid: error: internal error ({type(exc).__name__}: {one_line(str(exc))}); "
            "rerun with --verbose for the traceback",
            file=sys.stderr,
        )
        log.info("the error above came from here:", exc_info=exc)
        return 2
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
