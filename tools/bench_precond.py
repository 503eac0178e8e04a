"""Benchmark preconditioners of the Stage-1 shading solve on real photos.

For every size the full system of alternation 1 (all four priors, matting base = the smoothed
image) and of alternation 3 (``p.alternation(3)``, matting base = a reflectance estimate) is
solved by PCG from the cold start of ``solve_shading`` (the target mean), with

* ``jacobi``     -- the inverse diagonal (what ``solve_shading`` uses today, without its
                    coarse-to-fine warm start);
* ``amg``        -- :class:`~torchiid.solvers.multigrid.AMGPreconditioner` (pyamg smoothed
                    aggregation, CPU; setup includes assembling the scipy matrix);
* ``torch-mg``   -- :class:`~torchiid.solvers.multigrid.GalerkinMultigrid` (torch only);
* ``hsc``        -- :class:`~torchiid.solvers.multigrid.HSCPreconditioner` (Krishnan et al.);
* ``*-reuse``    -- alternation 1's preconditioner applied to alternation 3's matrix (no setup);
* ``shipped``    -- ``solve_shading`` with ``Parameters().shading`` as the pipeline
                    runs it (cascadic Jacobi PCG, capped): its iterations and final residual.

Columns: setup seconds, iterations to relative residual 1e-4 and 1e-5, solve seconds to 1e-4
and to 1e-5, total = setup + solve to 1e-4, and max|ds|: the largest error of the log-shading
at relative residual 1e-4 against a float64 solve to 1e-10, modulo the mean (``solve_shading``
shifts the mean afterwards; the anchor is below float32 resolution).

    python tools/bench_precond.py --sizes 256 512 1024
    OMP_NUM_THREADS=1 python tools/bench_precond.py --sizes 256 --threads 1
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import time
import warnings

import torch
import torch.nn.functional as F

from torchiid.core.colour import srgb_to_linear
from torchiid.core.exceptions import ConvergenceWarning
from torchiid.features.semantic import semantic_features
from torchiid.params import Parameters
from torchiid.priors.matting import smooth_base
from torchiid.solvers.multigrid import (
    AMGPreconditioner,
    GalerkinMultigrid,
    HSCPreconditioner,
    StencilOperator,
    pcg_callable,
)
from torchiid.stages import ShadingProblem, build_shading_system, solve_shading
from torchiid.stages.shading import anchored_system


def photo(name: str, width: int) -> torch.Tensor:
    import skimage.data

    rgb = getattr(skimage.data, name)()
    img = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
    return F.interpolate(srgb_to_linear(img), size=(width * 3 // 4, width), mode="area")


def timed_solve(system, precond, tol: float, max_iter: int):  # noqa: ANN001, ANN201
    """PCG to ``tol``; returns the result and the wall time at each iteration."""
    stamps: list[float] = []
    inner = precond

    def wrapped(r: torch.Tensor) -> torch.Tensor:
        stamps.append(time.perf_counter())
        return inner * r if isinstance(inner, torch.Tensor) else inner(r)

    t0 = time.perf_counter()
    res = pcg_callable(
        system.matvec,
        system.rhs,
        system.x0,
        wrapped,
        tol=tol,
        max_iter=max_iter,
        snapshot_tols=(1e-4,),
    )
    end = time.perf_counter()
    # preconditioner call k (0-based) happens in iteration k; iteration k ends before call k+1
    ends = stamps[1:] + [end]
    return res, t0, ends


def reference(system):  # noqa: ANN001, ANN201
    """The solution to relative residual 1e-10 in float64 (torch multigrid PCG)."""
    op = StencilOperator.from_quadratic(system.total, system.extra, dtype=torch.float64)
    res = pcg_callable(
        op.matvec,
        system.rhs.double(),
        system.x0.double(),
        GalerkinMultigrid(op),
        tol=1e-10,
        max_iter=200,
    )
    return res.x


def row(name: str, setup: float, res, t0: float, ends: list[float], ref=None) -> str:  # noqa: ANN001
    out = []
    for tol in (1e-4, 1e-5):
        it = res.iterations_to(tol)
        out.append((it, ends[it - 1] - t0 if it > 0 else float("nan")))
    err = ""
    if ref is not None and 1e-4 in res.snapshots:
        # solve_shading shifts s to the target mean afterwards: compare modulo the mean
        x = res.snapshots[1e-4].double()
        d = (x - x.mean()) - (ref - ref.mean())
        err = f"{float(d.abs().max()):9.1e}"
    (i4, s4), (i5, s5) = out
    i4s = f"{i4:>6}" if i4 >= 0 else f"{'>' + str(res.iterations):>6}"
    i5s = f"{i5:>6}" if i5 >= 0 else f"{'>' + str(res.iterations):>6}"
    return f"{name:<16} {setup:8.2f} {i4s} {i5s} {s4:8.2f} {s5:8.2f} {setup + s4:8.2f} {err}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024], help="widths")
    ap.add_argument("--image", default="chelsea", help="skimage.data photo (chelsea, coffee)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    ap.add_argument("--max-iter", type=int, default=4000, help="PCG cap (Jacobi needs it)")
    ap.add_argument("--skip", nargs="*", default=[], help="rows to skip (e.g. jacobi hsc)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore", ConvergenceWarning)
    p = Parameters()
    o = p.shading
    print(f"image={args.image} threads={torch.get_num_threads()} float32 PCG, cold start")
    head = (
        f"{'precond':<16} {'setup':>8} {'it1e-4':>6} {'it1e-5':>6} {'s@1e-4':>8} {'s@1e-5':>8} "
        f"{'total':>8} {'max|ds|':>9}"
    )
    for width in args.sizes:
        img = photo(args.image, width)
        h, w = img.shape[-2:]
        f = semantic_features(img, p)
        problem = ShadingProblem(img, f.patch_centers, f.patch_features, f.similarity, None, None)
        # a reflectance for alternation 3's matting base: the image over its smoothed intensity
        shade = smooth_base(img.mean(1, keepdim=True), 8.0).clamp_min(1e-3)
        refl = (img / shade).clamp(0, 4)
        problems = {1: problem, 3: problem.replace(base_image=smooth_base(refl, 1.0))}
        systems, precs = {}, {}
        for alt, pr in problems.items():
            built = build_shading_system(pr, p.alternation(alt)[0])
            systems[alt] = anchored_system(built.total, img, None, o.anchor, o.dark_eps)
        print(f"\n{w}x{h} ({h * w} px)")
        print(head)
        for alt in (1, 3):
            sy = systems[alt]
            print(f"-- alternation {alt}")
            ref = reference(sy)
            if "jacobi" not in args.skip:
                res, t0, ends = timed_solve(sy, sy.jacobi, 1e-5, args.max_iter)
                print(row("jacobi", 0.0, res, t0, ends, ref))
            cands = {
                "amg": lambda s: AMGPreconditioner.from_system(s.total, s.extra),
                "torch-mg": lambda s: GalerkinMultigrid.from_system(
                    s.total, s.extra, coarse_shift=1e-5
                ),
                "hsc": lambda s: HSCPreconditioner.from_system(s.total, s.extra),
            }
            for name, make in cands.items():
                if name in args.skip:
                    continue
                t = time.perf_counter()
                pre = make(sy)
                setup = time.perf_counter() - t
                precs[(name, alt)] = pre
                res, t0, ends = timed_solve(sy, pre, 1e-5, 400)
                print(row(name, setup, res, t0, ends, ref))
                if alt == 3:
                    res, t0, ends = timed_solve(sy, precs[(name, 1)], 1e-5, 400)
                    print(row(name + "-reuse", 0.0, res, t0, ends, ref))
            if "shipped" not in args.skip:
                pr = problems[alt]
                t = time.perf_counter()
                out = solve_shading(pr, p.alternation(alt)[0], warn=False)
                total = time.perf_counter() - t
                d = out.diagnostics
                build = sum(v for k, v in d.times.items() if k not in ("solve", "coarse"))
                print(
                    f"{'shipped':<16} {'':>8} {d.iterations:>6} {'':>6} {total - build:8.2f} "
                    f"{'':>8} {total - build:8.2f}  (levels={o.coarse_levels}, "
                    f"max_iter={o.cg_max_iter}, residual {float(d.residual.max()):.1e})"
                )


if __name__ == "__main__":
    main()
