"""Study: Split-Bregman against restarted fast ADMM on one photo's first reflectance solve.

Usage: ``python tools/study_fast_admm.py [--image chelsea] [--size 256]``

Runs the ``converged`` preset up to its first Split-Bregman solve, then solves that problem
(Eq. 12, the pipeline's terms) in plain torch with the terms' materialised operators, at the
preset's fixed θ, from ``z = ρ`` and the zero state, to a relative duality gap of 0.5%:
Split-Bregman as :func:`torchiid.solvers.split_bregman.split_bregman` iterates it, and the
fast ADMM with restart of Goldstein, O'Donoghue, Setzer & Baraniuk (2014, Algorithm 8,
η = 0.999), each with 5 and with 20 CG steps per ``z`` step. It prints the outer iterations
each needs. A study (README, "Solving to tolerance", stop 29), not part of the library: the
fast ADMM needs two more per-pair states (the previous ``d`` and ``b``), which the library's
compiled update does not keep.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import math
import time


def _shrink(x, lam):
    return x.sign() * (x.abs() - lam).clamp_min(0)


def solve(rho, terms, gammas, gamma_a, theta, accelerated, cg_iter, tol=0.005, cap=300):
    """Outer iterations to a relative gap ``tol`` (and the gap reached)."""

    from torchiid.solvers.pcg import pcg

    act = [(t, g) for t, g in zip(terms, gammas, strict=True) if g > 0]
    bsz, c, h, w = rho.shape
    deg = sum(t.normal_diagonal() for t, _ in act)
    pre = (1.0 / (2 * gamma_a + theta * deg)).expand(bsz, c, h, w).reshape(bsz * c, 1, h, w)

    def matvec(x):
        xi = x.view(bsz, c, h, w)
        out = sum(t.normal_matvec(xi) for t, _ in act)
        return (out * theta + 2 * gamma_a * xi).view(bsz * c, 1, h, w)

    lams = [g / theta for _, g in act]
    z = rho.clone()
    kz = [t.apply(z) for t, _ in act]
    d = [_shrink(k, lam) for k, lam in zip(kz, lams, strict=True)]
    b = [k - x for k, x in zip(kz, d, strict=True)]
    d_hat, b_hat, d_old, b_old = [x.clone() for x in d], [x.clone() for x in b], d, b
    alpha, c_old = 1.0, math.inf
    gap = math.nan
    for it in range(1, cap + 1):
        rhs = 2 * gamma_a * rho + theta * sum(
            t.adjoint(x - y) for (t, _), x, y in zip(act, d_hat, b_hat, strict=True)
        )
        z = pcg(
            matvec,
            rhs.reshape(bsz * c, 1, h, w),
            x0=z.reshape(bsz * c, 1, h, w),
            precond=pre,
            tol=1e-6,
            max_iter=cg_iter,
            warn=False,
            true_residual=False,
        )
        z = z.x.view(bsz, c, h, w)  # fmt: skip
        kz = [t.apply(z) for t, _ in act]
        d_new = [_shrink(k + x, lam) for k, x, lam in zip(kz, b_hat, lams, strict=True)]
        b_new = [x + k - y for x, k, y in zip(b_hat, kz, d_new, strict=True)]
        g = theta * sum(t.adjoint(x) for (t, _), x in zip(act, b_new, strict=True))
        primal = gamma_a * float((z - rho).square().sum())
        primal += sum(gg * float(t.l1(z).sum()) for t, gg in act)
        dual = float((g * rho).sum()) - float(g.square().sum()) / (4 * gamma_a)
        gap = (primal - dual) / primal
        if gap < tol:
            return it, gap
        if not accelerated:
            d_hat, b_hat = d_new, b_new
            continue
        combined = sum(float((x - y).square().sum()) for x, y in zip(b_new, b_hat, strict=True))
        combined += sum(float((x - y).square().sum()) for x, y in zip(d_new, d_hat, strict=True))
        if combined < 0.999 * c_old:
            alpha_new = (1 + math.sqrt(1 + 4 * alpha * alpha)) / 2
            beta = (alpha - 1) / alpha_new
            d_hat = [x + beta * (x - y) for x, y in zip(d_new, d_old, strict=True)]
            b_hat = [x + beta * (x - y) for x, y in zip(b_new, b_old, strict=True)]
            alpha, c_old = alpha_new, combined
        else:  # restart from the last accepted iterate
            alpha, c_old = 1.0, c_old / 0.999
            d_hat, b_hat = [x.clone() for x in d_old], [x.clone() for x in b_old]
            d_new, b_new = d_old, b_old
        d_old, b_old = d_new, b_new
    return cap, gap


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", default="chelsea", help="a skimage.data image")
    ap.add_argument("--size", type=int, default=256, help="long side (4:3)")
    args = ap.parse_args()
    import torch
    from skimage import data, transform

    import torchiid.stages.reflectance as stage
    from torchiid.model import decompose
    from torchiid.params import Parameters

    class _Captured(Exception):
        pass

    def capture(rho, terms, gammas, **kw):
        print(f"terms {[type(t).__name__ for t in terms]}, γ {gammas}, γ_a {kw['gamma_a']:g}, "
              f"θ {kw['theta']:g}")  # fmt: skip
        print("method              CG/step  iterations   gap     s")
        for accelerated in (False, True):
            for cg in (5, 20):
                t0 = time.perf_counter()
                its, gap = solve(rho, terms, gammas, kw["gamma_a"], kw["theta"], accelerated, cg)
                name = "fast ADMM, restart" if accelerated else "Split-Bregman"
                print(f"{name:20s} {cg:6d} {its:11d} {gap:7.4f} {time.perf_counter() - t0:5.1f}")
        raise _Captured

    stage.split_bregman = capture
    img = getattr(data, args.image)()
    img = transform.resize(img, (args.size * 3 // 4, args.size), anti_aliasing=True)
    x = torch.from_numpy(img).permute(2, 0, 1)[None].float()
    try:
        decompose(x, Parameters.preset("converged"))
    except _Captured:
        pass


if __name__ == "__main__":
    main()
