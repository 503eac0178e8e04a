"""Check the certified distance of the ``converged`` preset's Split-Bregman solves.

Usage: ``python tools/check_distance.py PHOTO [PHOTO ...] [--tight 1e-4]``

Runs :func:`torchiid.model.decompose` with the ``converged`` preset and, at every
alternation, solves the same reflectance problem once more from the same start to a much
smaller duality gap (``--tight``), then prints, per alternation, the bound the solve reports
(``SolveReport.distance``: ``‖z − z*‖ / ‖ρ‖`` from its duality gap and the data term's
strong convexity) next to the distance it actually has to the tight solution, the largest
single-value difference, and the reference's own certified distance (the measured one is
only known to within it). The tight solves make this slow (minutes per photo).
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", nargs="+")
    ap.add_argument("--tight", type=float, default=1e-4, help="duality gap of the reference")
    args = ap.parse_args()
    import torchiid.stages.reflectance as stage
    from torchiid.io import load_image
    from torchiid.model import decompose
    from torchiid.params import Parameters

    real = stage.split_bregman
    rows: list[tuple[int, float, float, float, float, float]] = []

    def checked(rho, terms, gammas, **kw):
        # the reference starts from the same warm state: keep a copy and put it back after
        saved = [(t, t.state.clone()) for t in terms if getattr(t, "state", None) is not None]
        steps = [
            (t, getattr(t, "state_step", None), getattr(t, "state_written", None)) for t in terms
        ]
        ref = real(rho, terms, gammas, **{**kw, "gap_tol": args.tight, "max_outer": 5000})
        for t, s in saved:
            t.state.copy_(s)
        for t, step, written in steps:
            if step is not None:
                t.state_step = step
            if written is not None:
                t.state_written = written
        res = real(rho, terms, gammas, **kw)
        true = float((res.z - ref.z).flatten(1).norm(dim=1).div(rho.flatten(1).norm(dim=1)).max())
        worst = float((res.z - ref.z).abs().max())
        its, gap = int(res.outer_iterations.max()), float(res.gap.max())
        rows.append((its, gap, float(res.distance.max()), true, worst, float(ref.distance.max())))
        return res

    stage.split_bregman = checked
    params = Parameters.preset("converged")
    # "true" is measured against the reference, itself certified only to within "ref"
    print(f"{'photo':24s} alt  its    gap  bound ‖z−z*‖/‖ρ‖   true  max |Δz|      ref")
    for path in args.photos:
        rows.clear()
        decompose(load_image(path).image, params)
        for k, (its, gap, bound, true, worst, ref) in enumerate(rows, 1):
            name = path.rsplit("/", 1)[-1] if k == 1 else ""
            print(
                f"{name:24s} {k:3d} {its:4d} {gap:6.4f} {bound:14.4%} {true:7.4%} {worst:9.4f}"
                f" {ref:8.4%}"
            )


if __name__ == "__main__":
    main()
