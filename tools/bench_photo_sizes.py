"""Time and peak memory of ``torchiid decompose`` on photos of 0.5 to 24 megapixels.

Each photo is a 2x2 mosaic of real photographs shipped with scikit-image (astronaut, coffee,
chelsea, rocket), resized to the target size and saved as a JPEG (quality 92), like a phone
photo. Every run is a fresh ``torchiid decompose`` process with the default settings (what a
user gets), so the figures include start-up, reading the JPEG, the method at its working
resolution, bringing the layers to full size and writing every output file. Peak RSS is the
child process's ``ru_maxrss``.

    python tools/bench_photo_sizes.py                     # 0.5, 2, 12 and 24 MP, 1 run each
    python tools/bench_photo_sizes.py --sizes 12 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from skimage import data

#: megapixels -> (width, height), 4:3 like a phone camera
SIZES = {0.5: (816, 612), 2: (1632, 1224), 12: (4032, 3024), 24: (5664, 4248)}


def mosaic(width: int, height: int) -> np.ndarray:
    """A ``height x width`` RGB uint8 mosaic of four real photos."""
    photos = [data.astronaut(), data.coffee(), data.chelsea(), data.rocket()]
    hw, hh = width // 2, height // 2
    tiles = [
        cv2.resize(p, (hw if i % 2 == 0 else width - hw, hh if i < 2 else height - hh),
                   interpolation=cv2.INTER_CUBIC)
        for i, p in enumerate(photos)
    ]  # fmt: skip
    top = np.concatenate(tiles[:2], axis=1)
    bottom = np.concatenate(tiles[2:], axis=1)
    return np.concatenate([top, bottom], axis=0)


def run_once(photo: Path, out: Path, extra: list[str]) -> tuple[float, float, float]:
    """``(wall seconds, peak RSS in GB, seconds in info.json)`` of one CLI run."""
    cmd = [sys.executable, "-m", "torchiid.cli", "decompose", str(photo), "-o", str(out)]
    cmd += ["--no-progress", "--overwrite", *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode() if proc.stderr else ""
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"torchiid failed on {photo}:\n{err}")
    info = json.loads((out / f"{photo.stem}-info.json").read_text())
    return wall, usage.ru_maxrss * 1024 / 1e9, float(info["seconds"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=sorted(SIZES))
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("extra", nargs="*", help="extra options for torchiid decompose (after --)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for mp in args.sizes:
            if mp not in SIZES:
                raise SystemExit(f"unknown size {mp}; choose from {sorted(SIZES)}")
            w, h = SIZES[mp]
            photo = Path(tmp) / f"photo-{w}x{h}.jpg"
            cv2.imwrite(str(photo), mosaic(w, h)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 92])
            # a fresh output folder per run: in a used one the manifest makes a rerun skip it
            runs = [
                run_once(photo, Path(tmp) / f"out-{w}x{h}-{i}", args.extra)
                for i in range(args.repeats)
            ]
            wall = statistics.median(r[0] for r in runs)
            rss = max(r[1] for r in runs)
            method = statistics.median(r[2] for r in runs)
            rows.append((mp, f"{w}x{h}", wall, method, rss))
            print(f"  {w}x{h}: {wall:.1f} s, {rss:.2f} GB", file=sys.stderr, flush=True)
    print(f"threads: {os.environ.get('OMP_NUM_THREADS', 'torch default')}, runs: {args.repeats}")
    print("| photo | pixels | wall time (process) | load + decompose | peak RSS |")
    print("| --- | --- | --- | --- | --- |")
    for mp, size, wall, method, rss in rows:
        print(f"| {mp:g} MP | {size} | {wall:.1f} s | {method:.1f} s | {rss:.2f} GB |")


if __name__ == "__main__":
    main()
