"""How much of an MIT object's bright albedo ends up in the shading, per parameter set.

    python tools/shading_level.py ../shared/data/mit-berkeley/teabag2 '{}' '{"t_e": 0}'

For each JSON object of parameter changes (over ``--preset``, default ``default``) the object
(``diffuse.png`` under ``mask.png``) is decomposed and the log-shading error
``log S - log S_true`` is averaged over the brightest tenth of the ground-truth albedo (print,
labels) and over its darker half; their difference is printed. 0: the shading's level does not
depend on the albedo, as it should; +0.53: the bright albedo came out e^0.53 = 1.7x brighter
in the shading than it is. Also prints the object's LMSE.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import json
from pathlib import Path

import torch

from torchiid.eval import mit_lmse
from torchiid.io import load_image, load_mask
from torchiid.model import decompose
from torchiid.params import Parameters


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="one MIT-Berkeley object's folder")
    ap.add_argument("changes", nargs="+", help="JSON objects of parameter changes")
    ap.add_argument("--preset", default="default")
    args = ap.parse_args()
    d = args.folder
    image = load_image(d / "diffuse.png", linear=True).image[None]
    mask = load_mask(d / "mask.png")[None]
    refl = load_image(d / "reflectance.png", linear=True).image[None]
    shading = load_image(d / "shading.png", linear=True).image[None].mean(1, keepdim=True)
    lum = refl.mean(1, keepdim=True)
    inside = mask.bool()
    bright = inside & (lum > torch.quantile(lum[inside], 0.9))
    dark = inside & (lum < torch.quantile(lum[inside], 0.5))
    for text in args.changes:
        params = Parameters.preset(args.preset).replace(**json.loads(text))
        out = decompose(image, params, mask=mask)
        err = out.shading.clamp_min(1e-6).log() - shading.clamp_min(1e-6).log()
        level = float(err[bright].mean() - err[dark].mean())
        lmse = float(mit_lmse(refl, shading, out.reflectance, out.shading, mask)[0])
        print(json.dumps({"changes": json.loads(text), "level": round(level, 3), "lmse": lmse}))


if __name__ == "__main__":
    main()
