"""Texture left in the shading: textured planes with known layers, and textured photos.

For each parameter set (presets side by side, ``--preset default paper``; ``--changes`` applies
to all of them) every image is decomposed and the shading scored with
:func:`torchiid.eval.texture_in_shading` (sigma 3 px, at the image's resolution):

- the ten planes of :func:`torchiid.synthetic_texture.texture_set` (``--size`` px square),
  against their true shading over the whole image: the share of the texture's fine-scale
  log-amplitude that the shading carries (0: none, 1: all), with the MIT LMSE beside it;
- ``skimage.data`` photos, without ground truth, inside a rectangle where the light can be
  taken as smooth at that scale (:data:`PHOTOS`): the share of the log-luminance's fine-scale
  variation there that the shading carries. Texture in relief (brick mortar joints are also
  grooves) is partly true shading, so a photo's figure is an upper bound of its texture in
  the shading.

    python tools/texture_check.py --preset default paper converged --cache texture-cache
    python tools/texture_check.py --preset default 'default:{"t_x": 0.05}'

Results are cached like ``tools/cv_mit.py``'s (JSON lines keyed by the full parameters, the
image and the code version).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import skimage.data
import torch

from torchiid.core.colour import srgb_to_linear
from torchiid.core.exceptions import TorchiidError
from torchiid.eval import mit_lmse, texture_in_shading
from torchiid.eval.crossval import JsonlCache, format_table
from torchiid.io import save_image
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.synthetic_texture import texture_set

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cv_mit import code_version, key_params  # noqa: E402

#: skimage.data photos and a region (rows y0:y1, columns x0:x1) of smooth light and fine texture
PHOTOS = {
    "brick": (0, 512, 0, 512),  # a brick wall: light mortar joints, evenly lit
    "coffee": (120, 400, 490, 600),  # the wooden table right of the saucer: grain
    "chelsea": (10, 110, 190, 340),  # the cat's forehead: tabby stripes in fur
    "astronaut": (348, 428, 135, 212),  # the embroidered mission patch on the suit
    "page": (40, 140, 0, 384),  # printed text on a page
    "text": (95, 172, 0, 448),  # handwriting on paper, the evenly lit lower part
}


def photo(name: str) -> torch.Tensor:
    """A ``skimage.data`` photo as ``(1, 3, H, W)`` linear RGB."""
    a = getattr(skimage.data, name)()
    if a.ndim == 2:
        a = np.stack([a] * 3, -1)
    x = torch.from_numpy(np.ascontiguousarray(a[..., :3])).permute(2, 0, 1).float() / 255
    return srgb_to_linear(x)[None]


def images(size: int) -> dict:
    """``{name: (image, true shading or None, region or None)}``."""
    out = {}
    for name, s in texture_set(size, size).items():
        out[name] = (s.image, s.shading, s.reflectance)
    for name, (y0, y1, x0, x1) in PHOTOS.items():
        img = photo(name)
        region = torch.zeros(1, 1, *img.shape[-2:], dtype=torch.bool)
        region[..., y0:y1, x0:x1] = True
        out[name] = (img, None, region)
    return out


def measure(image, truth, extra, params: Parameters, save: Path | None, tag: str) -> dict:
    """The texture measure (and, with a true shading, the MIT LMSE) of one decomposition."""
    t0 = time.perf_counter()
    out = decompose(image, params, return_stage1=False)
    seconds = time.perf_counter() - t0
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
        s = out.shading / out.shading.flatten(1).quantile(0.99, 1).view(-1, 1, 1, 1)
        save_image(save / f"{tag}-shading.png", s.clamp(0, 1)[0])
    if truth is None:
        t = texture_in_shading(out.shading, image, region=extra).item()
        return {"texture": t, "lmse": None, "seconds": round(seconds, 2)}
    t = texture_in_shading(out.shading, image, truth).item()
    lmse = mit_lmse(extra, truth, out.reflectance, out.shading).item()
    return {"texture": t, "lmse": lmse, "seconds": round(seconds, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--preset",
        nargs="+",
        default=["default"],
        help='presets side by side; PRESET:{"name": value} adds changes to one column',
    )
    ap.add_argument("--changes", default="{}", help="JSON object of changes for every preset")
    ap.add_argument("--size", type=int, default=256, help="side of the synthetic planes (256)")
    ap.add_argument("--cache", type=Path, help="folder of the JSON-lines result cache")
    ap.add_argument("--save", type=Path, help="write each shading as PNG here")
    ap.add_argument("--code-version", help="the cache keys' code version (see cv_mit.py)")
    args = ap.parse_args()
    try:
        changes = json.loads(args.changes)
        columns = {}
        for col in args.preset:
            name, _, extra = col.partition(":")
            columns[col] = Parameters.preset(name).replace(**changes, **json.loads(extra or "{}"))
    except (ValueError, TypeError, TorchiidError) as exc:
        raise SystemExit(f"error: {exc}") from None
    cache = JsonlCache(args.cache, "texture.jsonl")
    code = args.code_version or code_version()
    data = images(args.size)
    results: dict[str, dict[str, dict]] = {n: {} for n in data}
    for p, params in columns.items():
        for name, (image, truth, extra) in data.items():
            key = cache.key(
                params=key_params(params),
                image=name,
                size=args.size,
                code=code,
                threads=torch.get_num_threads(),
            )
            rec = cache.get(key)
            if rec is None:
                rec = measure(image, truth, extra, params, args.save, f"{p}-{name}")
                cache.put(
                    key,
                    {**rec, "image": name, "column": p, "code": code, "params": params.to_dict()},
                )
                print(f"  {p:<10} {name:<16} {rec['texture']:.4f} {rec['seconds']:5.1f} s",
                      file=sys.stderr, flush=True)  # fmt: skip
            results[name][p] = rec
    print(f"# texture in the shading (0: none, 1: all of the image's); changes {args.changes}; "
          f"code {code}\n")  # fmt: skip
    synthetic = [n for n in data if data[n][1] is not None]
    photos = [n for n in data if data[n][1] is None]
    for title, names, key in (
        (f"textured planes ({args.size} px), against the true shading", synthetic, "texture"),
        ("textured planes, MIT LMSE (½ shading + ½ gray reflectance)", synthetic, "lmse"),
        ("skimage.data photos, inside the region of smooth light", photos, "texture"),
    ):
        rows = [[n] + [results[n][p][key] for p in columns] for n in names]
        rows.append(
            ["**mean**"] + [float(np.mean([r[i + 1] for r in rows])) for i in range(len(columns))]
        )
        print(f"## {title}\n\n{format_table(['image', *columns], rows)}\n")


if __name__ == "__main__":
    main()
