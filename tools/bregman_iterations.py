"""Split-Bregman iterations of the full method, per photo and alternation, for parameter sets.

Usage: python tools/bregman_iterations.py [--preset converged] [--size 512]
       '{}' '{"theta": 5.0}' ... [chelsea rocket ... | photo.jpg ...]

Each argument that starts with ``{`` is a set of changes over ``Parameters.preset(--preset)``
(none: ``{}``); every photo is decomposed with each set (k = 5, features included) and the
outer Bregman iterations of each alternation are read from ``Decomposition.solves``. The other
arguments are photos: image files at their own size, or ``skimage.data`` names, cropped to 4:3
and resized to ``--size`` as ``tools/bench_decompose.py`` makes them (none: six of them).
Prints one line per photo and parameter set, then per set the total iterations, the wall time
and whether every solve converged.

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
    totals = []
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
            print(f"  {text:<40} {name:<22} {' '.join(f'{i:4d}' for i in its)}  = {sum(its)}")
        totals.append((text, total, seconds, converged))
    print(f"{'changes':<40} {'iterations':>10} {'seconds':>8}  all converged")
    for text, total, seconds, converged in totals:
        print(f"{text:<40} {total:>10d} {seconds:>8.1f}  {converged}")


if __name__ == "__main__":
    main()
