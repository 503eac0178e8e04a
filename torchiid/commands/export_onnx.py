"""``torchiid export-onnx``: write the ONNX feature extractor and record its hash."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

__all__ = ["DESCRIPTION", "add_arguments", "run"]

DESCRIPTION = (
    "Export the CNN feature extractor (EfficientNet-Lite0) to ONNX and record its SHA-256 in "
    "the manifest."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``torchiid export-onnx``."""
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="where to write (default: the cache used by the library)",
    )


def run(args: argparse.Namespace) -> int:
    """Run ``torchiid export-onnx``; returns the exit status."""
    from torchiid.features.onnx_backend import ensure_onnx_model, export_to_dir

    t0 = time.perf_counter()
    path = export_to_dir(args.output) if args.output else ensure_onnx_model()
    if not getattr(args, "quiet", False):
        print(f"wrote {path} ({time.perf_counter() - t0:.1f} s)")
    return 0
