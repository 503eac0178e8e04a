"""Temporal consistency on MPI Sintel and on the synthetic moving Mondrian: warping error
(Lai et al. 2018) of the reflectance, frame by frame against the video loop's variants.

    OMP_NUM_THREADS=2 python tools/eval_sintel_video.py ../shared/data/sintel-clean
    OMP_NUM_THREADS=2 python tools/eval_sintel_video.py --synthetic

Sintel (clean pass, 1024x436, four frames per sequence, default parameters, working
resolution 512): the warping error of the reflectance in sRGB [0, 1] over the three pairs with
flow estimated on the input frames (OpenCV DIS at full resolution), and over the pair 2 -> 3
with the ground-truth flow and occlusions (gt/frame_0002.flo, gt/occlusions_0002.png).
Synthetic (the tests' moving Mondrian, 96x72 x 5 frames and 192x144 x 12 frames, light turning
0.1 rad per frame): the warping error with the true flow and occlusions and with the estimated
flow, and the mean MIT LMSE against the true layers.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import sys
import time
from pathlib import Path

import cv2
import torch

from torchiid.eval.lmse import mit_lmse
from torchiid.eval.video import read_flo, warping_error
from torchiid.io import load_image
from torchiid.params import Parameters
from torchiid.synthetic import moving_mondrian
from torchiid.video import VideoDecomposer, VideoOptions

FB = VideoOptions.frame_by_frame()
SCALE = FB.replace(match_scale=True)
CONFIGS = {
    "frame by frame": FB,
    "+ one scale": SCALE,
    "+ one scale + warm start": SCALE.replace(warm_start=True),
    "+ one scale + L2 1 (no warm start)": SCALE.replace(temporal_weight=1.0),
    "+ one scale + L2 4 (no warm start)": SCALE.replace(temporal_weight=4.0),
    "+ one scale + L2 16 (no warm start)": SCALE.replace(temporal_weight=16.0),
    "+ one scale + L1 0.2 (no warm start)": SCALE.replace(temporal_weight=0.2, temporal_norm="l1"),
    "+ one scale + L1 1 (no warm start)": SCALE.replace(temporal_weight=1.0, temporal_norm="l1"),
    "+ one scale + L1 2 (no warm start)": SCALE.replace(temporal_weight=2.0, temporal_norm="l1"),
    "default (one scale, warm start, L2 4, Stage 0 reuse, 2 alternations)": VideoOptions(),
    "default with the last 3 alternations": VideoOptions(later_iterations=3),
    "default with L1 0.2": VideoOptions(temporal_norm="l1", temporal_weight=0.2),
    "default with L1 1": VideoOptions(temporal_norm="l1", temporal_weight=1.0),
    "default with all 5 alternations": VideoOptions(later_iterations=0),
    "default, warm start without the median": VideoOptions(init_median=0),
    "default with target_sigma 2": VideoOptions(target_sigma=2.0),
    "default without Stage 0 reuse": VideoOptions(reuse_features=False),
}


def run(frames, params, options):
    video = VideoDecomposer(params, options)
    out = []
    t0 = time.perf_counter()
    for img in frames:
        out.append(video(img))
    return out, time.perf_counter() - t0


def sintel(root: Path, names: list[str], params: Parameters) -> None:
    print("| sequence | variant | WE estimated flow (3 pairs) | WE GT flow 2->3 | s |")
    print("| --- | --- | --- | --- | --- |")
    for seq in sorted(p for p in root.iterdir() if (p / "gt").is_dir()):
        frames = [load_image(f).image for f in sorted(seq.glob("frame_*.png"))]
        gt = read_flo(seq / "gt" / "frame_0002.flo")
        occ = cv2.imread(str(seq / "gt" / "occlusions_0002.png"), cv2.IMREAD_GRAYSCALE)
        occ = torch.from_numpy(occ > 127)[None, None]
        for name in names:
            res, secs = run(frames, params, CONFIGS[name])
            refl = [f.reflectance for f in res]
            est = warping_error(refl, frames)
            g = warping_error(refl[1:3], flows=[gt], occlusions=[occ])
            print(f"| {seq.name} | {name} | {est.mean:.5f} | {g.mean:.5f} | {secs:.1f} |")
            sys.stdout.flush()
        inp = warping_error(frames, frames)
        g = warping_error(frames[1:3], flows=[gt], occlusions=[occ])
        print(f"| {seq.name} | (input frames) | {inp.mean:.5f} | {g.mean:.5f} | |")


def synthetic(names: list[str], params: Parameters) -> None:
    print("| size | variant | WE true flow | WE estimated flow | mean LMSE | s |")
    print("| --- | --- | --- | --- | --- | --- |")
    for h, w, n in ((72, 96, 5), (144, 192, 12)):
        seq = moving_mondrian(h, w, frames=n, velocity=(3, 1), light_step=0.1)
        frames = list(seq.images)
        flows = [seq.flow[t : t + 1] for t in range(n - 1)]
        occl = [~seq.valid[t : t + 1] for t in range(n - 1)]
        for name in names:
            res, secs = run(frames, params, CONFIGS[name])
            refl = [f.reflectance for f in res]
            g = warping_error(refl, flows=flows, occlusions=occl)
            est = warping_error(refl, frames)
            lm = [
                float(
                    mit_lmse(
                        seq.reflectance[t : t + 1], seq.shading[t : t + 1], f.reflectance, f.shading
                    )
                )
                for t, f in enumerate(res)
            ]
            print(
                f"| {w}x{h}, {n} frames | {name} | {g.mean:.5f} | {est.mean:.5f} "
                f"| {sum(lm) / n:.5f} | {secs:.1f} |"
            )
            sys.stdout.flush()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", type=Path, nargs="?", help="the sintel-clean folder")
    ap.add_argument("--synthetic", action="store_true", help="the moving Mondrian instead")
    ap.add_argument("--variants", nargs="*", default=list(CONFIGS), help="which rows")
    ap.add_argument("--iterations", type=int, help="alternations (default: the preset's)")
    args = ap.parse_args()
    params = Parameters()
    if args.iterations:
        params = params.replace(iterations=args.iterations)
    if args.synthetic:
        synthetic(args.variants, params)
    else:
        if args.root is None:
            ap.error("give the sintel-clean folder or --synthetic")
        sintel(args.root, args.variants, params)


if __name__ == "__main__":
    main()
