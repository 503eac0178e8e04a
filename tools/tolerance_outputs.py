"""How much the ``converged`` preset's outputs move with Split-Bregman's duality-gap tolerance.

Usage: ``python tools/tolerance_outputs.py PHOTO [PHOTO ...] [--gaps 0.005 0.02 0.05]
[--reference 0.0005] [--early GAP [GAP ...]]``

Decomposes every photo (sRGB decoded to linear, as ``torchiid decompose`` reads it) with
``--preset converged`` once per tolerance (``bregman_gap_tol``)
and once with the much smaller ``--reference`` tolerance, and prints, per photo and tolerance,
the seconds, the Split-Bregman iterations (over the five alternations, and per alternation),
and how far the files
a user opens are from the reference's: the 8-bit sRGB reflectance (the ``-reflectance.png``
encoding; largest difference in code values, 99.9th percentile, and the share of pixel
values that differ by more than one code) and the shading, as relative differences of the
linear shading (99.9th percentile and largest). A tolerance is loose enough to use where the
reflectance stays within about one code value of the reference's everywhere but a few pixels.

``--early GAP ...``: a study of a looser tolerance for the intermediate alternations only. After
each tolerance's row come rows where the Split-Bregman solves of alternations 1 .. k − 1 stop
at ``GAP`` and only the last one at the row's tolerance (the reference keeps its tolerance
everywhere). It wraps the pipeline's ``solve_reflectance``; no preset does this.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photos", nargs="+")
    ap.add_argument("--gaps", type=float, nargs="+", default=[0.005, 0.02, 0.05])
    ap.add_argument("--reference", type=float, default=0.0005)
    ap.add_argument(
        "--early", type=float, nargs="*", default=[], help="gaps of alternations 1..k-1"
    )
    args = ap.parse_args()
    import dataclasses

    import numpy as np

    import torchiid.model as model
    from torchiid.core.colour import linear_to_srgb
    from torchiid.io import load_image
    from torchiid.params import Parameters

    solve = model.solve_reflectance
    calls = {"early": None, "n": 0, "last": 0}

    def solve_early_loose(problem, weights, options, **kw):
        calls["n"] += 1
        if calls["early"] is not None and calls["n"] < calls["last"]:
            options = dataclasses.replace(options, gap_tol=calls["early"])
        return solve(problem, weights, options, **kw)

    model.solve_reflectance = solve_early_loose

    def run(image, gap, early=None):
        params = Parameters.preset("converged").replace(bregman_gap_tol=gap)
        calls.update(early=early, n=0, last=params.iterations)
        t0 = time.perf_counter()
        out = model.decompose(image, params)
        seconds = time.perf_counter() - t0
        outer = [r.iterations for r in out.solves if r.stage == "reflectance"]
        return out, seconds, f"{sum(outer)} ({', '.join(map(str, outer))})"

    def code(r):
        return (linear_to_srgb(r.clamp(0, 1)) * 255).round()

    print(
        "| photo | gap | s | Bregman iterations | reflectance: max / 99.9% code diff | "
        "values > 1 code apart | shading: 99.9% / max relative diff |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for path in args.photos:
        image = load_image(path).image[None]  # sRGB decoded to linear, as the CLI does
        ref, ref_s, ref_n = run(image, args.reference)
        ref_code = code(ref.reflectance)
        name = path.rsplit("/", 1)[-1]
        print(f"| {name} | {args.reference:g} (reference) | {ref_s:.1f} | {ref_n} | | | |")
        for gap in args.gaps:
            for early in [None, *args.early]:
                out, s, n = run(image, gap, early)
                diff = (code(out.reflectance) - ref_code).abs().flatten()
                rel = ((out.shading - ref.shading).abs() / ref.shading.clamp_min(1e-6)).flatten()
                label = f"{gap:g}" if early is None else f"{gap:g}, earlier alternations {early:g}"
                print(
                    f"| {name} | {label} | {s:.1f} | {n} | {float(diff.max()):.0f} / "
                    f"{np.quantile(diff.numpy(), 0.999):.0f} | "
                    f"{float((diff > 1).float().mean()) * 100:.3f}% | "
                    f"{np.quantile(rel.numpy(), 0.999) * 100:.1f}% / "
                    f"{float(rel.max()) * 100:.0f}% |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
