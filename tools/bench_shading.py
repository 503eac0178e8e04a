"""Benchmark the Stage-1 shading solve (all four terms) on synthetic Mondrian images.

Prints one row per size: build time per term, solve time, iterations, time per iteration,
final relative residual, correlation of the recovered log-shading with the truth, and the
process's peak resident memory so far (sizes run in increasing order).

    python tools/bench_shading.py --sizes 256 512 1024 --threads 2 --levels 5
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import resource
import time
import warnings

import torch

from torchiid.core.exceptions import ConvergenceWarning
from torchiid.params import ShadingParameters
from torchiid.priors.lle import patch_rgb_features
from torchiid.priors.shading_terms import shading_stencil
from torchiid.stages.config import ShadingProblem
from torchiid.stages.shading import solve_shading
from torchiid.synthetic import mondrian


def inputs(width: int, device: str):
    h, w = width * 3 // 4, width
    syn = mondrian(h, w, seed=1, patches=20, device=device)
    st = shading_stencil(h, w, device=device)
    # mid-level similarity from one-hot "proposals" (the rectangles), as MidLevelFeatures would give
    g = torch.nn.functional.one_hot(syn.labels, 32).permute(0, 3, 1, 2).float()
    sim = (g.unsqueeze(2) * st.neighbours(g)).sum(1)
    ys, xs = torch.arange(15, h, 30, device=device), torch.arange(15, w, 30, device=device)
    ctr = torch.stack(torch.meshgrid(ys, xs, indexing="ij"), -1).reshape(-1, 2)
    feats = patch_rgb_features(syn.image, ctr, patch_size=60)  # strategy p1 features
    return syn, ShadingProblem(syn.image, patch_centers=ctr, patch_features=feats, similarity=sim)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024], help="widths")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--levels", type=int, default=5)
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--max-iter", type=int, default=300)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore", ConvergenceWarning)
    head = (
        f"{'size':>10} {'px':>8} {'S_c':>6} {'S_p':>6} {'S_m':>6} {'S_l':>6} {'coarse':>7} "
        f"{'solve':>7} {'total':>7} {'iters':>6} {'ms/it':>6} {'resid':>8} {'corr':>6} "
        f"{'peakMB':>7}"
    )
    print(f"threads={args.threads} levels={args.levels} tol={args.tol} max_iter={args.max_iter}")
    print(head)
    # the paper's weights (all four priors on, no S_s), without the pixel confidence and the
    # colour-edge cut, the paper's matting base
    weights = ShadingParameters(
        lambda_m=0.02, lambda_s=0.0, t_e=0.0, dark_level=0.0, clip_level=0.0, base_mix=1.0
    )
    options = weights.replace(
        cg_tol=args.tol, cg_max_iter=args.max_iter, warm_cg_max_iter=0, coarse_levels=args.levels
    )
    for width in args.sizes:
        syn, problem = inputs(width, args.device)
        warm_up = ShadingProblem(syn.image[..., :32, :32])
        solve_shading(warm_up, weights.replace(cg_tol=1e-2, cg_max_iter=5, coarse_levels=5))
        t0 = time.perf_counter()
        res = solve_shading(problem, options)
        total = time.perf_counter() - t0
        d = res.diagnostics
        s, gt = res.log_shading.flatten(), syn.shading.log().flatten()
        corr = float(torch.corrcoef(torch.stack([s, gt]))[0, 1])
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6  # KiB -> MB
        t = d.times
        h, w = syn.image.shape[-2:]
        print(
            f"{f'{w}x{h}':>10} {h * w:>8} {t.get('S_c', 0):6.3f} {t.get('S_p', 0):6.3f} "
            f"{t.get('S_m', 0):6.3f} {t.get('S_l', 0):6.3f} {t.get('coarse', 0):7.3f} "
            f"{t['solve']:7.3f} {total:7.3f} {d.iterations:>6} "
            f"{1000 * t['solve'] / max(d.iterations, 1):6.2f} {float(d.residual.max()):8.1e} "
            f"{corr:6.3f} {peak:7.0f}"
        )


if __name__ == "__main__":
    main()
