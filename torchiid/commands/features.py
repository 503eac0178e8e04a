"""``torchiid features``: pictures of the Stage 0 semantic features of one photo."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from torchiid.commands.common import add_overwrite_and_linear

__all__ = ["DESCRIPTION", "OUTPUTS", "add_arguments", "run"]

DESCRIPTION = (
    "Write the PCA image of the mid-level features g_i, proposal masks and the patch grid of "
    "one photo, and print the time of every step."
)

OUTPUTS = ("gpca.png", "proposals.png", "patch-grid.png")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``torchiid features``."""
    p.add_argument("input", type=Path, help="an image file")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    p.add_argument(
        "--mode",
        default="shared",
        choices=["shared", "crop"],
        help="patch features: shared (one CNN pass over the whole image, pooled per patch; "
        "the default) or crop (each patch resized and run on its own, the paper's protocol)",
    )
    add_overwrite_and_linear(p)


def run(args: argparse.Namespace) -> int:
    """Run ``torchiid features``; returns the exit status."""
    from torchiid.core.device import resolve_device
    from torchiid.core.exceptions import TorchiidError
    from torchiid.features.midlevel import midlevel_features
    from torchiid.features.patches import patch_features, patch_grid
    from torchiid.features.proposals import selective_search
    from torchiid.features.visualize import (
        draw_patch_grid,
        overlay_masks,
        pca_image,
        select_masks,
    )
    from torchiid.io import linear_to_srgb, load_image, save_uint8
    from torchiid.io.layers import OutputSet, check_output_folder

    device = resolve_device(args.device)
    out = args.output
    check_output_folder(out)
    stem = args.input.stem
    targets = [out / f"{stem}-{name}" for name in OUTPUTS]
    for t in targets:
        if t.is_dir() and not t.is_symlink():
            raise TorchiidError(f"{t}: is a folder; cannot replace it by an output")
    existing = [t for t in targets if t.exists()]
    if existing and not args.overwrite:
        raise TorchiidError(f"{existing[0]} exists; pass --overwrite to replace it")
    timings: list[tuple[str, float]] = []

    t0 = time.perf_counter()
    loaded = load_image(args.input, linear=args.linear)
    image = loaded.image[None].to(device)
    timings.append(("load image", time.perf_counter() - t0))
    h, w = image.shape[-2:]

    t0 = time.perf_counter()
    grid = patch_grid(h, w)
    feats = patch_features(image, mode=args.mode)
    timings.append(
        (f"patch features f_b ({args.mode}, {len(grid)} patches)", time.perf_counter() - t0)
    )

    t0 = time.perf_counter()
    props = selective_search(image.cpu()[0])
    timings.append(
        (
            f"selective search ({props.num_proposals} proposals, {props.num_atoms} atoms)",
            time.perf_counter() - t0,
        )
    )

    t0 = time.perf_counter()
    mid = midlevel_features(props)
    gpca = pca_image(mid)
    timings.append(("mid-level g_i + PCA", time.perf_counter() - t0))

    srgb = linear_to_srgb(loaded.image).permute(1, 2, 0).numpy()
    t0 = time.perf_counter()
    overlay = overlay_masks(srgb, props.masks(select_masks(props, 4)), columns=2)
    pictures = [gpca, overlay, draw_patch_grid(srgb, grid.boxes)]
    with OutputSet(out, overwrite=args.overwrite, label=stem) as tx:  # all three or none
        for target, picture in zip(targets, pictures, strict=True):
            tx.write(target.name, lambda p, picture=picture: save_uint8(p, picture))
        tx.commit()
    timings.append(("write pictures", time.perf_counter() - t0))

    width = max(len(n) for n, _ in timings)
    print(f"{'step':<{width}}  seconds")
    for name, sec in timings:
        print(f"{name:<{width}}  {sec:7.3f}")
    print(f"{'total':<{width}}  {sum(s for _, s in timings):7.3f}")
    print(f"features f_b: {tuple(feats.features.shape)}; g_i: {mid.num_proposals} proposals")
    if not getattr(args, "quiet", False):
        for t in targets:
            print(f"wrote {t}")
    return 0
