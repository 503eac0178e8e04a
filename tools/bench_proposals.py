"""Benchmark selective search and the mid-level features g_i on a 512x384 photo (CPU).

Usage:
    python tools/bench_proposals.py [--image astronaut|chelsea|coffee] [--repeats 3]
        [--threads N] [--scales 100] [--colour-spaces hsv lab] [--similarities ctsf tsf]

Prints one table row per image: the best-of-``repeats`` wall time of ``selective_search`` and
of ``midlevel_features`` + ``pca(8)`` + ``similarity`` (3x3 half stencil), their sum, the sum's
process CPU time (best of ``repeats``; close to the wall time of an idle machine with
``--threads 1``), the numbers of atoms and proposals, and the process's peak resident memory
(``ru_maxrss``, imports included).
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import os
import resource
import time

import numpy as np
import torch
from skimage import data, transform

from torchiid.features.midlevel import midlevel_features
from torchiid.features.proposals import selective_search
from torchiid.priors.stencil import Stencil


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6  # KiB -> MB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", nargs="+", default=["astronaut", "chelsea", "coffee"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    ap.add_argument("--scales", type=float, nargs="+", default=None)
    ap.add_argument("--colour-spaces", nargs="+", default=None)
    ap.add_argument("--similarities", nargs="+", default=None)
    ap.add_argument("--max-proposals", type=int, default=None)
    ap.add_argument("--pca-dim", type=int, default=8)
    args = ap.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    kw = {}
    if args.scales:
        kw["scales"] = tuple(args.scales)
    if args.colour_spaces:
        kw["colour_spaces"] = tuple(args.colour_spaces)
    if args.similarities:
        kw["similarities"] = tuple(args.similarities)
    if args.max_proposals:
        kw["max_proposals"] = args.max_proposals
    print(
        f"torch threads: {torch.get_num_threads()}, load average: {os.getloadavg()[0]:.2f}, "
        f"options: {kw or 'defaults'}"
    )
    rss0 = _rss_mb()
    header = (
        f"{'image':<10} {'H x W':>9} {'search s':>9} {'g_i s':>7} {'total s':>8} "
        f"{'cpu s':>8} {'atoms':>6} {'props':>6} {'peak RSS MB':>12}"
    )
    print(header)
    print("-" * len(header))
    stencil = Stencil.square(384, 512, 3)
    for name in args.image:
        img = transform.resize(getattr(data, name)(), (384, 512), anti_aliasing=True)
        img = np.clip(img, 0.0, 1.0)
        t_ss, t_g, c_ss, c_g = [], [], [], []
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            props = selective_search(img, **kw)
            t1, c1 = time.perf_counter(), time.process_time()
            mid = midlevel_features(props)
            mid.pca(args.pca_dim)
            mid.similarity(stencil)
            t2, c2 = time.perf_counter(), time.process_time()
            t_ss.append(t1 - t0)
            t_g.append(t2 - t1)
            c_ss.append(c1 - c0)
            c_g.append(c2 - c1)
        a, b = min(t_ss), min(t_g)
        ca, cb = min(c_ss), min(c_g)
        print(
            f"{name:<10} {'384x512':>9} {a:9.3f} {b:7.3f} {a + b:8.3f} {ca + cb:8.3f} "
            f"{props.num_atoms:6d} {props.num_proposals:6d} {_rss_mb():12.0f}"
        )
    print(f"RSS after imports: {rss0:.0f} MB")


if __name__ == "__main__":
    main()
