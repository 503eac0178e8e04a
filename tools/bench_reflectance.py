"""Benchmark Stage 2 (reflectance, Split-Bregman) at 512x384.

Usage: python tools/bench_reflectance.py [--height 384] [--width 512] [--repeat 3] [--threads N]

Prints a table: time for r̄ (feat), v_l, v_m, the terms (operator set-up, Q and v^g),
Split-Bregman time, outer/CG iterations,
peak memory (CPU: max RSS growth via resource; CUDA: torch.cuda.max_memory_allocated).
The input is a synthetic Mondrian (torchiid.synthetic.mondrian) with noisy rho, a piecewise-
constant 8-d g-feature map and Felzenszwalb segments.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import resource
import time

import torch

from torchiid.features.segmentation import felzenszwalb_segments
from torchiid.params import ReflectanceParameters
from torchiid.stages.config import ReflectanceProblem
from torchiid.stages.reflectance import solve_reflectance
from torchiid.synthetic import mondrian


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--height", type=int, default=384)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--max-outer", type=int, default=3)
    ap.add_argument("--cg-max-iter", type=int, default=5)
    ap.add_argument("--window", type=int, default=11)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    s = mondrian(args.height, args.width, patches=20, seed=1, device=dev)
    g = torch.Generator(device="cpu").manual_seed(0)
    rho = (s.reflectance + 0.03 * torch.randn(s.reflectance.shape, generator=g).to(dev)).clamp(0, 1)
    codes = torch.randn(int(s.labels.max()) + 1, 8, generator=g).to(dev) * 0.02
    gpca = codes[s.labels].permute(0, 3, 1, 2).contiguous()
    t0 = time.perf_counter()
    segments = felzenszwalb_segments(s.image)
    t_seg = time.perf_counter() - t0

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    problem = ReflectanceProblem(rho, s.image, gpca=gpca, segments=segments)
    # the paper's gammas
    options = ReflectanceParameters(
        bregman_iter=args.max_outer, bregman_cg_iter=args.cg_max_iter, window=args.window
    )
    variants = [
        ("A", options.replace(gamma_m=0, gamma_g=0), True),
        ("A+B merged", options.replace(gamma_g=0), True),
        ("A+B+C merged", options, True),
        ("A+B+C separate", options, False),
    ]
    print(
        f"image {args.width}x{args.height}, device {dev}, threads {torch.get_num_threads()}, "
        f"window {args.window}, felzenszwalb {t_seg * 1000:.0f} ms "
        f"({int(segments.max()) + 1} segments)"
    )
    hdr = (
        f"{'variant':<16} {'feat ms':>8} {'v_l ms':>7} {'v_m ms':>7} {'terms ms':>8} "
        f"{'SB ms':>7} {'total ms':>9} {'outer':>5} {'CG':>4} {'|Q|':>5} {'obj0':>10} "
        f"{'objT':>10} {'RMSE rho':>9} {'RMSE R':>8}"
    )
    print(hdr)
    print("-" * len(hdr))
    for name, opts, merge in variants:
        best = None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            r = solve_reflectance(problem, opts, merge=merge)
            if dev.type == "cuda":
                torch.cuda.synchronize()
            total = time.perf_counter() - t0
            if best is None or total < best[0]:
                best = (total, r)
        total, r = best
        tm = r.timings
        rm0 = float((rho - s.reflectance).square().mean().sqrt())
        rm1 = float((r.reflectance - s.reflectance).square().mean().sqrt())
        print(
            f"{name:<16} {tm.features * 1e3:8.1f} {tm.weights_local * 1e3:7.1f} "
            f"{tm.weights_mid * 1e3:7.1f} {tm.weights_global * 1e3:8.1f} {tm.solve * 1e3:7.1f} "
            f"{total * 1e3:9.1f} {int(r.solver.outer_iterations.max()):5d} "
            f"{r.solver.cg_iterations:4d} {int(r.num_representatives.max()):5d} "
            f"{float(r.solver.objective[0, 0]):10.1f} {float(r.solver.objective[-1, 0]):10.1f} "
            f"{rm0:9.4f} {rm1:8.4f}"
        )
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6
    if dev.type == "cuda":
        print(f"peak CUDA memory: {torch.cuda.max_memory_allocated() / 1e6:.0f} MB")
    print(f"peak RSS: {rss1:.0f} MB (growth during the runs: {rss1 - rss0:.0f} MB)")


if __name__ == "__main__":
    main()
