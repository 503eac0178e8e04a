"""Render the front page's figures: ``input | reflectance | shading`` for three photos, one edit.

Usage::

    python tools/make_figures.py [-o docs/images] [--side 240]

Decomposes three photos shipped with scikit-image (``coffee``, ``chelsea``, ``astronaut``) with
the default parameters, as ``torchiid decompose`` would, and writes
``decomposition-<photo>.jpg``: the input, the reflectance and the viewable shading
(``S / shading_white``) side by side, 8-bit sRGB, ``--side`` pixels high, JPEG quality 85.
Then recolours the coffee cup (its red reflectance turned by 120 degrees of hue, the shading
kept; the mask is chosen by colour, as a user would paint it) and writes
``edit-recolour.jpg`` (input | result). Prints each file with its size in KB; every file is
meant to stay under 250 KB. About 20 s on 2 CPU cores.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
from pathlib import Path

import numpy as np
import torch
from edit_gallery import colour_mask, photo
from PIL import Image

from torchiid import Parameters, decompose, edit
from torchiid.core.colour import linear_to_srgb

PHOTOS = ("coffee", "chelsea", "astronaut")


def save_panels(path: Path, panels: list[torch.Tensor], side: int) -> None:
    """Write linear ``(1, C, H, W)`` panels side by side as an sRGB JPEG ``side`` px high."""
    sep = torch.ones(3, panels[0].shape[-2], 6)
    row = torch.cat([p for x in panels for p in (x[0].expand(3, -1, -1).clamp(0, 1), sep)][:-1], 2)
    arr = (linear_to_srgb(row).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    img = Image.fromarray(arr)
    img = img.resize((round(img.width * side / img.height), side), Image.LANCZOS)
    img.save(path, quality=85, optimize=True)
    print(f"{path}  {path.stat().st_size / 1024:.0f} KB")


def main() -> None:
    """Render the figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=Path("docs/images"))
    ap.add_argument("--side", type=int, default=240, help="height of the JPEGs in pixels")
    args = ap.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    params = Parameters()
    for name in PHOTOS:
        img = photo(name)
        out = decompose(img, params)
        view = out.shading / out.shading_white.view(-1, 1, 1, 1)
        panels = [img, out.reflectance, view]
        save_panels(args.output / f"decomposition-{name}.jpg", panels, args.side)
        if name == "coffee":
            mask = colour_mask(name, img)
            result = edit.recolour(out.reflectance, out.shading, mask, hue=120)[0]
            save_panels(args.output / "edit-recolour.jpg", [img, result], args.side)


if __name__ == "__main__":
    main()
