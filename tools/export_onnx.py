"""Export the EfficientNet-Lite0 feature extractor to ONNX and update the manifest.

Usage: python tools/export_onnx.py [--output-dir models/]

Writes ``<output-dir>/efficientnet_lite0_features.onnx`` (not committed: ``models/*.onnx`` is
ignored by git) and records its SHA-256, opset, input/output names and the SHA-256 of the
source ``.pth`` weights in ``<output-dir>/manifest.json`` (committed).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from torchiid.features.onnx_backend import export_to_dir


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output-dir", type=Path, default=Path("models"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    path = export_to_dir(args.output_dir)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) and {path.parent / 'manifest.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
