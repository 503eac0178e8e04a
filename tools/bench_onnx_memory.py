"""What onnxruntime's CPU arena holds after a Stage 0 feature pass, with and without the shrink.

:class:`~torchiid.features.onnx_backend.OnnxFeatureExtractor` asks onnxruntime to shrink its
CPU arena at the end of each call (``release_memory=True``, the default), so the activation
buffers of the feature pass are not held through the solves that follow. This runs the
extractor on sRGB inputs of a few sizes in a fresh process each and prints, as a Markdown
table, the resident memory (``/proc/self/statm``, Linux) after a pass that keeps the arena and
after one that shrinks it.

    python tools/bench_onnx_memory.py                   # 512x512 and 1024x768
    python tools/bench_onnx_memory.py --sizes 256x256   # a smoke test

Run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

_CHILD = r"""
import json, os, sys
import torch
from torchiid.features.onnx_backend import OnnxFeatureExtractor

def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6

h, w = map(int, sys.argv[1].split("x"))
x = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
extractor = OnnxFeatureExtractor(intra_op_threads=1)
extractor(x, release_memory=False)
held = rss_mb()
extractor(x)
released = rss_mb()
print(json.dumps({"held": held, "released": released}))
"""


def main(argv: list[str] | None = None) -> int:
    """Print the table; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["512x512", "1024x768"], help="HxW")
    args = parser.parse_args(argv)
    if not sys.platform.startswith("linux"):
        print("needs /proc/self/statm (Linux)", file=sys.stderr)
        return 1
    print("| input | RSS, arena kept (MB) | RSS, arena shrunk (MB) | given back (MB) |")
    print("| --- | ---: | ---: | ---: |")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for size in args.sizes:
        run = subprocess.run(
            [sys.executable, "-c", _CHILD, size], capture_output=True, text=True, env=env
        )
        if run.returncode != 0:
            print(run.stderr, file=sys.stderr)
            return run.returncode
        got = json.loads(run.stdout.strip().splitlines()[-1])
        held, released = got["held"], got["released"]
        print(f"| {size} | {held:.0f} | {released:.0f} | {held - released:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
