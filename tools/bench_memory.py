"""Peak memory of ``torchiid decompose`` against the estimate its memory check uses.

Usage: python tools/bench_memory.py [--sizes 0.5 1 2] [--presets default converged]
       [--max-side 0]

For every preset and size (megapixels; 4:3 JPEG mosaics of scikit-image photos, as
``tools/bench_photo_sizes.py`` makes them) a fresh ``torchiid decompose`` process runs with
``--max-side`` (default 0: the method at full resolution, where the memory grows most), and
its peak RSS is read from ``wait4``. A run on a 128x96 photo with the same preset gives the
process's own footprint (libraries, feature extractor); the growth above it is compared with
:func:`torchiid.model.memory_needed`, the estimate that ``decompose`` checks against the
memory available before it starts (with Stage 1's layers, which the command keeps for
``-sigma.exr``). A ratio above 1 means the estimate is conservative.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_photo_sizes import SIZES as PHOTO_SIZES  # noqa: E402
from bench_photo_sizes import mosaic  # noqa: E402

from torchiid.model import memory_needed  # noqa: E402
from torchiid.params import Parameters  # noqa: E402

#: megapixels -> (width, height), 4:3: those of bench_photo_sizes, and 1 and 4 MP
SIZES = {**PHOTO_SIZES, 1: (1152, 864), 4: (2304, 1728)}


def _peak_rss(photo: Path, out: Path, preset: str, max_side: int) -> tuple[float, int]:
    """``(peak RSS in bytes, exit status)`` of one ``torchiid decompose`` process."""
    cmd = [sys.executable, "-m", "torchiid.cli", "decompose", str(photo), "-o", str(out)]
    cmd += ["--preset", preset, "--max-side", str(max_side), "--no-progress", "--overwrite"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return usage.ru_maxrss * 1024.0, proc.returncode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.5, 1, 2])
    ap.add_argument("--presets", nargs="+", default=["default", "converged"])
    ap.add_argument("--max-side", type=int, default=0)
    args = ap.parse_args()
    print(
        f"{'preset':<10} {'photo':>10} {'peak GB':>8} {'base GB':>8} {'growth GB':>9} "
        f"{'estimate GB':>11} {'estimate/growth':>15}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        tiny = d / "tiny.jpg"
        cv2.imwrite(str(tiny), mosaic(128, 96)[..., ::-1])
        for preset in args.presets:
            params = Parameters.preset(preset).replace(max_side=args.max_side)
            base, status = _peak_rss(tiny, d / f"out-{preset}-base", preset, args.max_side)
            if status != 0:
                print(f"{preset:<10} the run on a 128x96 photo failed (exit status {status})")
                continue
            for mp in args.sizes:
                w, h = SIZES[mp]
                photo = d / f"p{mp:g}.jpg"
                if not photo.exists():
                    rgb = mosaic(w, h)
                    cv2.imwrite(str(photo), rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 92])
                out = d / f"out-{preset}-{mp:g}"  # a fresh folder: no manifest to skip by
                peak, status = _peak_rss(photo, out, preset, args.max_side)
                est = memory_needed(h, w, params, return_stage1=True)  # as decompose checks
                growth = peak - base
                note = "" if status == 0 else f"  (exit status {status})"
                print(
                    f"{preset:<10} {f'{w}x{h}':>10} {peak / 1e9:>8.2f} {base / 1e9:>8.2f} "
                    f"{growth / 1e9:>9.2f} {est / 1e9:>11.2f} {est / max(growth, 1):>15.2f}{note}"
                )


if __name__ == "__main__":
    main()
