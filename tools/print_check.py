"""Black text on white paper: how much of the print ends up in the shading, per preset.

    python tools/print_check.py                      # default and print presets
    python tools/print_check.py --presets print '{"t_d": 1.0}'

The image is made here: scikit-image's ``text`` sample (black lettering on a light ground),
thresholded into ink and paper, strokes anti-aliased (Gaussian, 0.7 px), albedos
``(0.03, 0.03, 0.028)`` and ``(0.85, 0.82, 0.75)`` (linear), under a smooth light that varies
4.6x across the page; 344 x 896 px, so the default working resolution (512) resizes it as it
would a photo. Printed per parameter set: the ink's level in the log-shading relative to the
paper's (0 is right; -3.3 means all of the print went to the shading) and the ink/paper ratio
of the reflectance's channel mean (true: 0.036; 1 means no print in the reflectance).

Then the same ratios on a real photo, scikit-image's ``page`` (a photographed, unevenly lit
page of text; ink and paper found against a 15 px median of the page), at its size and
enlarged 3x (573 x 1152, which the method solves at 512 px and brings back to full size).
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import json

import numpy as np
import torch
from scipy.ndimage import gaussian_filter, median_filter
from skimage import data, transform

from torchiid.io import srgb_to_linear
from torchiid.model import decompose
from torchiid.params import Parameters

PAPER = np.array([0.85, 0.82, 0.75], np.float32)
INK = np.array([0.03, 0.03, 0.028], np.float32)


def document() -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """The page ``(1, 3, H, W)`` linear, its ink coverage and its true shading ``(H, W)``."""
    t = data.text().astype(np.float32) / 255
    t = transform.resize(t, (t.shape[0] * 2, t.shape[1] * 2), anti_aliasing=True)
    ink = gaussian_filter((t < 0.35).astype(np.float32), 0.7)
    h, w = ink.shape
    albedo = PAPER[:, None, None] * (1 - ink) + INK[:, None, None] * ink
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    shade = (0.25 + 0.9 * np.exp(-((xx - 0.3) ** 2 + (yy - 0.2) ** 2) / 0.3)).astype(np.float32)
    return torch.from_numpy(albedo * shade)[None], ink, shade


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("changes", nargs="*", default=["{}"], help="JSON parameter changes")
    ap.add_argument("--presets", default="default,print", help="comma-separated preset names")
    args = ap.parse_args()
    image, ink, shade = document()
    on_ink, on_paper = ink > 0.7, ink < 0.05
    print(f"{'preset':<10} {'changes':<22} {'ink level':>10} {'ink/paper':>10}  (true 0, 0.036)")
    for preset in args.presets.split(","):
        for text in args.changes:
            params = Parameters.preset(preset).replace(**json.loads(text))
            out = decompose(image, params)
            err = np.log(np.maximum(out.shading[0, 0].numpy(), 1e-6)) - np.log(shade)
            level = err[on_ink].mean() - err[on_paper].mean()
            r = out.reflectance[0].mean(0).numpy()
            ratio = r[on_ink].mean() / r[on_paper].mean()
            print(f"{preset:<10} {text:<22} {level:>10.2f} {ratio:>10.3f}")
    print(f"\n{'preset':<10} {'changes':<22} {'page':>6} {'R ink/paper':>12} {'S ink/paper':>12}")
    for scale in (1, 3):
        page = data.page().astype(np.float32) / 255
        if scale > 1:
            page = transform.resize(page, (page.shape[0] * scale, page.shape[1] * scale), order=3)
            page = page.astype(np.float32)
        ground = median_filter(page, size=15 * scale)
        ink_px, paper_px = page < 0.6 * ground, page > 0.95 * ground
        img = srgb_to_linear(torch.from_numpy(page)).expand(1, 3, *page.shape).contiguous()
        for preset in args.presets.split(","):
            for text in args.changes:
                params = Parameters.preset(preset).replace(**json.loads(text))
                out = decompose(img, params)
                r, s = out.reflectance[0].mean(0).numpy(), out.shading[0, 0].numpy()
                rr = r[ink_px].mean() / r[paper_px].mean()
                sr = s[ink_px].mean() / s[paper_px].mean()
                print(f"{preset:<10} {text:<22} {scale:>5}x {rr:>12.3f} {sr:>12.3f}")


if __name__ == "__main__":
    main()
