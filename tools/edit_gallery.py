"""Render the ``torchiid edit`` gallery: ``input | result`` for each operation.

Usage::

    python tools/edit_gallery.py [-o docs/images] [--iterations 2] [--max-side 320]

Decomposes two ``skimage.data`` photos once each (the coffee cup and the astronaut; 2
alternations at a 320 px working resolution by default) and writes
``edit-<photo>-<operation>.jpg`` for every operation of ``torchiid edit`` (input and result side
by side, 8-bit sRGB, JPEG quality 85), printing each path. The masks are chosen by colour, as a
user would paint them: the red cup and saucer, the orange suit. About a minute on 2 CPU cores.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from skimage import data

from torchiid import Parameters, decompose, edit
from torchiid.core.colour import linear_to_srgb, srgb_to_linear


def photo(name: str) -> torch.Tensor:
    """A ``skimage.data`` photo as a linear ``(1, 3, H, W)`` tensor."""
    arr = getattr(data, name)()[..., :3].astype(np.float32) / 255
    return srgb_to_linear(torch.from_numpy(arr).permute(2, 0, 1))[None]


def save_pair(path: Path, panels: list[torch.Tensor], side: int) -> None:
    """Write two linear panels side by side as an sRGB JPEG ``side`` px high."""
    sep = torch.ones(3, panels[0].shape[-2], 4)
    row = torch.cat([p for x in panels for p in (x[0].clamp(0, 1), sep)][:-1], 2)
    arr = (linear_to_srgb(row).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    img = Image.fromarray(arr)
    img.thumbnail((2 * side + 4, side))
    img.save(path, quality=85)


def colour_mask(name: str, img: torch.Tensor) -> torch.Tensor:
    """A user-like mask by colour: the red cup and saucer, or the orange suit."""
    from skimage.color import rgb2hsv
    from skimage.morphology import disk, opening

    srgb = linear_to_srgb(img[0]).permute(1, 2, 0).numpy()
    hsv = rgb2hsv(srgb)
    hue, sat, val = hsv[..., 0] * 360, hsv[..., 1], hsv[..., 2]
    if name == "coffee":  # the red cup and saucer
        sel = ((hue < 15) | (hue > 345)) & (sat > 0.6) & (val > 0.25)
    else:  # the orange suit
        sel = (hue > 5) & (hue < 30) & (sat > 0.55) & (val > 0.35)
    sel = opening(sel, disk(2)).astype(bool)
    return torch.from_numpy(sel)[None, None]


def main() -> None:
    """Render the gallery."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=Path("docs/images"))
    ap.add_argument("--iterations", type=int, default=2)
    ap.add_argument("--max-side", type=int, default=320, help="working resolution")
    ap.add_argument("--side", type=int, default=360, help="panel height in the JPEGs")
    args = ap.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    params = Parameters().replace(iterations=args.iterations, max_side=args.max_side)
    for name in ("coffee", "astronaut"):
        img = photo(name)
        d = decompose(img, params)
        m = edit.merge(img, d.reflectance, d.shading, d.sigma, d.rho)
        h, w = img.shape[-2:]
        mask = colour_mask(name, img)
        rm, sm = m.reflectance, m.shading
        tex = torch.from_numpy(data.brick().astype(np.float32) / 255)[None].expand(3, -1, -1)
        results = {
            "merge": (m.c - 1) * 10 + 0.5,
            "illumination-colour": edit.illumination_colour(rm, sm, "red", 0.5)[0],
            "illumination-intensity": edit.illumination_intensity(
                img, d.reflectance, d.shading, d.sigma, d.rho, 0.6, merged=m
            )[0],
            "remove-texture": edit.remove_texture(rm, sm, mask)[0],
            "replace-albedo": edit.replace_albedo(rm, sm, mask, srgb_to_linear(tex), scale=0.5)[0],
            "recolour": edit.recolour(rm, sm, mask, hue=120)[0],
            "soften-shadows": edit.soften_shadows(rm, sm, 0.6)[0],
        }
        for op, res in results.items():
            save_pair(args.output / f"edit-{name}-{op}.jpg", [img, res], args.side)
            print(args.output / f"edit-{name}-{op}.jpg")


if __name__ == "__main__":
    main()
