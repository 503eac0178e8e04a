"""Benchmark the compiled stencil kernels against the torch ops they replace.

Usage: python tools/bench_kernels.py [--sizes 256 512 1024] [--threads N] [--repeats 20]

For every size (the long side, 4:3) prints the median milliseconds of one call, torch ops
against the kernel (:mod:`torchiid.priors.kernels`), for the calls the solvers spend their
time in: the shading system's 5×5 stencil product (12 offsets, one channel, the PCG's
matvec), the reflectance ``z`` step's 11×11 product (60 offsets, 3 channels, squared
weights), the matting Laplacian's 5×5 stencil from its base image (once per alternation),
the ``default`` preset's second Split-Bregman update of a solve (the kernel replays the
first update instead of reading and writing the stored 60-offset state), the stored updates,
and 20 Jacobi-preconditioned PCG iterations on a 5×5 stencil system, for one image (the
shading solves) and three (the ``z`` step's channels): the fused iteration
(:mod:`torchiid.solvers.pcg_fused`) with the kernel's product against the torch ops for both.
The torch column is measured with the kernels switched off, as ``TORCHIID_KERNELS=torch`` does.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import statistics
import time

import torch

from torchiid.priors import kernels
from torchiid.priors.matting import matting_stencil
from torchiid.priors.quadratic import StencilQuadratic
from torchiid.priors.reflectance_terms import StencilL1Term
from torchiid.priors.stencil import Stencil, half_offsets
from torchiid.solvers import pcg_fused
from torchiid.solvers.pcg import pcg


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm-up (compilation, allocator)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def _cases(h: int, w: int):
    """``(name, call)``: the same call runs with the kernels and with the torch ops, except
    the Bregman update, whose torch path updates a stored state instead of replaying it."""
    g = torch.Generator().manual_seed(0)
    st5 = Stencil(h, w, half_offsets(5))
    q = StencilQuadratic(st5, torch.randn(1, st5.num_offsets, h, w, generator=g))
    x = torch.randn(1, 1, h, w, generator=g)
    st11 = Stencil.square(h, w, 11)
    weights = torch.rand(1, st11.num_offsets, h, w, generator=g) * st11.valid
    l1 = StencilL1Term(st11, weights)
    z = torch.rand(1, 3, h, w, generator=g)
    z1 = torch.rand(1, 3, h, w, generator=g)
    base = torch.rand(1, 3, h, w, generator=g)
    # the default preset's second (and last) Bregman update of a solve: replayed from the
    # first update's z (kernels), or read from the stored state and written back (torch)
    lean = StencilL1Term(st11, weights, keep_state=False)
    replay, _, _ = lean.bregman_step(z, None, 0.05, with_l1=False)
    stored = StencilL1Term(st11, weights)
    state, _, _ = stored.bregman_step(z, None, 0.05, with_l1=False)

    def update():
        if kernels.usable(z1):
            return lean.bregman_step(z1, replay, 0.05, with_l1=False, final=True)
        return stored.bregman_step(z1, state, 0.05, with_l1=False)

    # the converged preset's updates: a stored state read and written (float32, and the
    # pipeline's 16-bit fixed point)
    shape = (1, 3, st11.num_offsets, h, w)
    f32 = StencilL1Term(st11, weights, state=torch.zeros(shape), warm=True, replay=False)
    i16 = StencilL1Term(st11, weights, state=torch.zeros(shape, dtype=torch.int16), warm=True,
                        state_step=kernels.fixed_point_scales(0.05)[0], replay=False)  # fmt: skip

    def pcg_case(images: int):
        # a weighted graph Laplacian plus a positive diagonal: SPD; 20 iterations, no stop
        lap = StencilQuadratic(st5, torch.rand(images, st5.num_offsets, h, w, generator=g))
        d = torch.rand(images, 1, h, w, generator=g) + 0.05
        minv = 1 / (d + lap.diagonal())
        b = torch.randn(images, 1, h, w, generator=g)
        return lambda: pcg(lambda v: d * v + lap.matvec(v), b, precond=minv, tol=1e-30,
                           max_iter=20, warn=False, true_residual=False)  # fmt: skip

    return [
        ("shading 5x5 product", lambda: q.matvec(x)),
        ("reflectance 11x11 product", lambda: l1.normal_matvec(z)),
        ("matting to stencil", lambda: matting_stencil(base)),
        ("Bregman update (2nd)", update),
        ("stored update, float32", lambda: f32.bregman_step(z1, f32.state, 0.05, False)),
        ("stored update, int16", lambda: i16.bregman_step(z1, i16.state, 0.05, False)),
        (
            "stored update, int16 + gap",
            lambda: i16.bregman_step(z1, i16.state, 0.05, False, stats=True),
        ),
        ("PCG x20, 1 image", pcg_case(1)),
        ("PCG x20, 3 images", pcg_case(3)),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if kernels._numba() is None:
        raise SystemExit("numba is not importable (or TORCHIID_KERNELS=torch is set)")
    print(f"median ms per call, {torch.get_num_threads()} threads")
    print(f"{'size':>9} {'product':<27} {'torch':>8} {'kernel':>8} {'speed-up':>8}")
    print("-" * 64)
    usable, applies = kernels.usable, pcg_fused.applies
    for side in args.sizes:
        h, w = side * 3 // 4, side
        for name, fn in _cases(h, w):
            fast = _median_ms(fn, args.repeats)
            kernels.usable = lambda *t, **k: False
            pcg_fused.applies = lambda *t, **k: False
            try:
                ref = _median_ms(fn, args.repeats)
            finally:
                kernels.usable, pcg_fused.applies = usable, applies
            print(f"{w}x{h:<5} {name:<27} {ref:8.2f} {fast:8.2f} {ref / fast:7.1f}x")


if __name__ == "__main__":
    main()
