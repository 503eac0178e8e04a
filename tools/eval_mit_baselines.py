"""LMSE of the trivial baselines and colour Retinex on MIT-Berkeley objects.

Protocol (Grosse et al. 2009): input ``diffuse.png`` under ``mask.png``; score
``½ LMSE(shading) + ½ LMSE(gray reflectance)`` with 20×20 windows, shift 10.
Baselines: ``R = I`` (reflectance = gray image, shading = 1) and ``S = I`` (shading = gray
image, reflectance = 1). Prints a per-object table, the means and the Retinex time per image.

    python tools/eval_mit_baselines.py [--root ../shared/data/mit-berkeley] [--threads 2]
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import time
from pathlib import Path

import torch

from torchiid.baselines import color_retinex
from torchiid.eval import MITDataset, mit_lmse

DEFAULT_ROOT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mit-berkeley"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    ap.add_argument("--repeats", type=int, default=3, help="Retinex time = min over repeats")
    ap.add_argument("--threshold-gray", type=float, default=0.075)
    ap.add_argument("--threshold-color", type=float, default=1.0)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    ds = MITDataset(args.root)
    rows = []
    for s in ds:
        img, mask = s.image[None], s.mask[None]
        gray = img.mean(dim=1, keepdim=True)
        ones = torch.ones_like(gray)
        dt = float("inf")
        for _ in range(max(args.repeats, 1)):
            t0 = time.perf_counter()
            out = color_retinex(img, mask, args.threshold_gray, args.threshold_color)
            dt = min(dt, time.perf_counter() - t0)
        gt = (s.reflectance[None], s.shading[None])
        rows.append(
            (
                s.id,
                f"{img.shape[-2]}x{img.shape[-1]}",
                float(mit_lmse(*gt, out.reflectance, out.shading, mask)),
                float(mit_lmse(*gt, gray, ones, mask)),
                float(mit_lmse(*gt, ones, gray, mask)),
                dt,
            )
        )
    print(f"{'object':<10} {'size':>8} {'Retinex':>8} {'R=I':>8} {'S=I':>8} {'t_ret[s]':>9}")
    for name, size, a, b, c, dt in rows:
        print(f"{name:<10} {size:>8} {a:8.4f} {b:8.4f} {c:8.4f} {dt:9.2f}")
    n = len(rows)
    means = [sum(r[k] for r in rows) / n for k in (2, 3, 4, 5)]
    print(f"{'mean':<10} {'':>8} {means[0]:8.4f} {means[1]:8.4f} {means[2]:8.4f} {means[3]:9.2f}")


if __name__ == "__main__":
    main()
