"""Split-Bregman iterations of the full method, per photo and alternation, for parameter sets.

Usage: python tools/bregman_iterations.py [--preset converged] [--size 512]
       '{}' '{"theta": 5.0}' ... [chelsea rocket ... | photo.jpg ...]

Each argument that starts with ``{`` is a set of changes over ``Parameters.preset(--preset)``
(none: ``{}``); every photo is decomposed with each set (k = 5, features included) and the
outer Bregman iterations of each alternation are read from ``Decomposition.solves``. The other
arguments are photos: image files at their own size, or ``skimage.data`` names, cropped to 4:3
and resized to ``--size`` as ``tools/bench_decompose.py`` makes them (none: six of them).
Prints one line per photo and parameter set (the iterations, then the seconds of Stage 0, of
the shading and of the reflectance stages, and the reflectance stages' milliseconds per Bregman
iteration, set-up included), then per set the total iterations, the wall time and whether every
solve converged. With ``--budget S`` a last table says, per photo, how many Bregman iterations
would fit in a wall time of ``S`` seconds at the measured cost per iteration, after the photo's
measured Stage 0 and shading (the floor of the target "converged in S seconds" for this
solver). A first, uncounted run loads the feature extractor and the compiled kernels.

The counts do not depend on the load or on the number of threads (the result of a solve does
not), so two sets can run at once (``OMP_NUM_THREADS=1``); the wall times
then only indicate the cost. Iterations are what a change of the solver's schedule or penalty
saves; the seconds follow them.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_decompose import _image  # noqa: E402

from torchiid.io import load_image  # noqa: E402
from torchiid.model import decompose  # noqa: E402
from torchiid.params import Parameters  # noqa: E402

DEFAULT_IMAGES = ["chelsea", "astronaut", "coffee", "rocket", "retina", "immunohistochemistry"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("items", nargs="*", help="JSON objects of changes, then photos")
    ap.add_argument("--preset", default="converged")
    ap.add_argument("--size", type=int, default=512, help="long side of the skimage photos")
    ap.add_argument(
        "--budget", type=float, default=0.0, help="a wall-time target in seconds (see above)"
    )
    args = ap.parse_args()
    changes = [a for a in args.items if a.lstrip().startswith("{")] or ["{}"]
    names = [a for a in args.items if not a.lstrip().startswith("{")] or DEFAULT_IMAGES
    photos = []
    for item in names:
        if Path(item).is_file():
            photos.append((Path(item).stem, lambda f=item: load_image(f).image[None]))
        else:
            photos.append((item, lambda n=item: _image(n, args.size)))
    base = Parameters.preset(args.preset)
    print(f"preset {args.preset}; outer Split-Bregman iterations per alternation")
    print(
        f"  {'changes':<40} {'photo':<22} iterations = total; seconds: Stage 0 and the rest / "
        "shading / reflectance; ms per iteration"
    )
    # one uncounted run first: loading the feature extractor and the compiled kernels
    decompose(_image("chelsea", 128), base)
    totals, rows = [], []
    for text in changes:
        params = base.replace(**json.loads(text))
        total, seconds, converged = 0, 0.0, True
        for name, load in photos:
            x = load()
            t0 = time.perf_counter()
            out = decompose(x, params)
            seconds += time.perf_counter() - t0
            its = [int(s.iterations) for s in out.solves if s.stage == "reflectance"]
            converged &= all(bool(s.converged) for s in out.solves)
            total += sum(its)
            stage0, shading, refl = _stage_seconds(out.times)
            per = 1e3 * refl / max(sum(its), 1)
            print(
                f"  {text:<40} {name:<22} {' '.join(f'{i:4d}' for i in its)}  = {sum(its)};"
                f"  {stage0:.2f} / {shading:.2f} / {refl:.2f} s; {per:.0f} ms"
            )
            rows.append((text, name, sum(its), stage0, shading, per))
        totals.append((text, total, seconds, converged))
    print(f"{'changes':<40} {'iterations':>10} {'seconds':>8}  all converged")
    for text, total, seconds, converged in totals:
        print(f"{text:<40} {total:>10d} {seconds:>8.1f}  {converged}")
    if args.budget > 0:
        print(
            f"\nwithin {args.budget:g} s: Bregman iterations that fit after the measured Stage 0 "
            "and shading, at the measured ms per iteration, against the iterations run"
        )
        print(f"{'changes':<40} {'photo':<22} {'left s':>7} {'fit':>5} {'ran':>5}")
        for text, name, ran, stage0, shading, per in rows:
            left = args.budget - stage0 - shading
            fit = max(int(1e3 * left / per), 0) if per > 0 else 0
            print(f"{text:<40} {name:<22} {left:>7.2f} {fit:>5d} {ran:>5d}")


def _stage_seconds(times: dict) -> tuple[float, float, float]:
    """Stage 0 (and the rest), shading and reflectance seconds of one decomposition's ``times``."""
    shading = sum(v for k, v in times.items() if k.startswith("shading "))
    refl = sum(v for k, v in times.items() if k.startswith("reflectance "))
    # Stage 0 and the rest (the layers' final steps): the total less the two stages
    return times["total"] - shading - refl, shading, refl


if __name__ == "__main__":
    main()
