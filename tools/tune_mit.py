"""Score parameter changes on the MIT-Berkeley objects, one JSON line per parameter set.

Each argument is a JSON object of changes over ``Parameters.preset(--preset)`` (default:
``default``); every object is decomposed
(``diffuse.png`` under ``mask.png``) and scored with the MIT LMSE. Prints the mean, the seconds
and the per-object scores, for tuning the energy with one parameter set for all images.

    python tools/tune_mit.py ../shared/data/mit-berkeley '{}' '{"lambda_l": 1.0}'
    python tools/tune_mit.py --preset converged ../shared/data/mit-berkeley '{"t_i": 0.6}'

``--per-alternation`` also scores every alternation's layers (``return_iterations``), at the
working resolution: objects larger than it are compared with their ground truth area-averaged
to it, so those scores differ a little from the final full-resolution ones.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from torchiid.eval import mit_lmse
from torchiid.io import load_image, load_mask
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.resample import downsample


def _score_low(it, refl, shading, mask) -> float:
    """LMSE of one alternation's working-resolution layers (ground truth area-averaged)."""
    if it.shading.shape[-2:] != refl.shape[-2:]:
        size = tuple(it.shading.shape[-2:])
        mask = downsample(mask.float(), size) > 0.5
        refl, shading = downsample(refl, size) * mask, downsample(shading, size) * mask
    return float(mit_lmse(refl, shading, it.reflectance, it.shading, mask)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="the MIT-Berkeley folder")
    ap.add_argument("changes", nargs="+", help="JSON objects of parameter changes")
    ap.add_argument("--preset", default="default", help="the preset the changes apply to")
    ap.add_argument(
        "--per-alternation", action="store_true", help="also score every alternation's layers"
    )
    args = ap.parse_args()
    objects = sorted(p.name for p in args.root.iterdir() if (p / "diffuse.png").is_file())
    samples = {}
    for name in objects:
        d = args.root / name
        image = load_image(d / "diffuse.png", linear=True).image[None]
        mask = load_mask(d / "mask.png")[None]
        refl = load_image(d / "reflectance.png", linear=True).image[None]
        shading = load_image(d / "shading.png", linear=True).image[None].mean(1, keepdim=True)
        samples[name] = (image, mask, refl, shading)
    for text in args.changes:
        changes = json.loads(text)
        params = Parameters.preset(args.preset).replace(**changes)
        t0 = time.perf_counter()
        rows, per_alt = {}, {}
        for name, (image, mask, refl, shading) in samples.items():
            out = decompose(image, params, mask=mask, return_iterations=args.per_alternation)
            rows[name] = float(mit_lmse(refl, shading, out.reflectance, out.shading, mask)[0])
            if args.per_alternation:
                per_alt[name] = [_score_low(it, refl, shading, mask) for it in out.iterations]
        mean = sum(rows.values()) / len(rows)
        record = {
            "changes": changes,
            "mean": round(mean, 5),
            "seconds": round(time.perf_counter() - t0, 1),
            "objects": {k: round(v, 5) for k, v in rows.items()},
        }
        if per_alt:
            k = len(next(iter(per_alt.values())))
            record["alternations"] = [
                round(sum(v[i] for v in per_alt.values()) / len(per_alt), 5) for i in range(k)
            ]
            record["objects_per_alternation"] = {
                n: [round(x, 5) for x in v] for n, v in per_alt.items()
            }
        print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
