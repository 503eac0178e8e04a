"""Benchmark the CNN patch features f_b on a 512x384 photo (CPU).

Usage: python tools/bench_features.py [--repeats 5] [--threads N]

Prints, per configuration, the median wall time of ``--repeats`` runs (after one warm-up run)
and the process's peak resident memory (``ru_maxrss``) after it; configurations run in
increasing memory order, so each peak is an upper bound for that configuration.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import resource
import statistics
import time

import torch
import torch.nn.functional as F
from kornia.color import rgb_to_linear_rgb
from skimage import data

from torchiid.features import OnnxFeatureExtractor, ensure_onnx_model, patch_features


def _image() -> torch.Tensor:
    srgb = torch.from_numpy(data.coffee()).permute(2, 0, 1)[None].float() / 255
    srgb = F.interpolate(srgb, size=(384, 512), mode="bilinear", antialias=True)
    return rgb_to_linear_rgb(srgb)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--no-crop", action="store_true", help="skip the slow crop mode")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    image = _image()
    onnx = OnnxFeatureExtractor(ensure_onnx_model())
    configs = [
        ("shared", "onnx", 1.0),
        ("shared", "onnx", 2.0),
        ("shared", "torch", 2.0),
        ("shared", "onnx", 3.0),
    ]
    if not args.no_crop:
        configs += [("crop", "onnx", 1.0), ("crop", "torch", 1.0)]
    print(f"image 512x384, torch threads {torch.get_num_threads()}, repeats {args.repeats}")
    print(f"{'mode':<7} {'backend':<7} {'scale':>5} {'patches':>7} {'median s':>9} {'peak MB':>8}")
    for mode, backend, scale in configs:
        times = []
        for _ in range(args.repeats + 1):
            start = time.perf_counter()
            out = patch_features(
                image, mode=mode, backend=backend, scale=scale, onnx_extractor=onnx
            )
            times.append(time.perf_counter() - start)
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6  # KiB -> MB
        scale_txt = f"{scale:.1f}" if mode == "shared" else "-"
        print(
            f"{mode:<7} {backend:<7} {scale_txt:>5} {out.features.shape[1]:>7} "
            f"{statistics.median(times[1:]):>9.3f} {peak_mb:>8.0f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
