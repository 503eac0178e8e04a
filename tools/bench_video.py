"""Speed of the video loop: later frames against a still decomposition of the same size.

    OMP_NUM_THREADS=2 python tools/bench_video.py                  # 512x384, 8 frames
    OMP_NUM_THREADS=2 python tools/bench_video.py --size 256x192 --frames 6 --repeats 1

The sequence is a camera pan over scikit-image's coffee photo (600x400): frame t is the
512x384 window shifted by (2, 1) px per frame, resized to --size. Each variant decomposes the
whole sequence once per repeat (a fresh VideoDecomposer, default Parameters, so the working
resolution is the frame's own at 512x384); "still" is torchiid.decompose on every frame alone
(the frame-by-frame baseline, features included). The table gives the first frame's seconds,
the mean of the later frames, and that mean over the still mean (the target: at most 0.60),
the same ratio in process CPU time (steadier on a busy machine with OMP_NUM_THREADS=1), then
where a later frame's time goes. Run it on an otherwise idle machine.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import statistics
import time

import cv2
import torch
from skimage import data

from torchiid.core.colour import srgb_to_linear
from torchiid.model import decompose
from torchiid.params import Parameters
from torchiid.video import VideoDecomposer, VideoOptions


def pan_frames(size: tuple[int, int], count: int, step: tuple[int, int] = (2, 1)):
    photo = data.coffee()  # 400 x 600
    w0, h0 = 512, 384
    frames = []
    for t in range(count):
        x0, y0 = 8 + step[0] * t, 4 + step[1] * t
        crop = photo[y0 : y0 + h0, x0 : x0 + w0]
        if crop.shape[:2] != (h0, w0):
            raise SystemExit(f"--frames {count} moves the window out of the photo")
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        x = torch.from_numpy(crop).permute(2, 0, 1).float() / 255
        frames.append(srgb_to_linear(x).contiguous())
    return frames


def time_video(frames, params, options):
    video = VideoDecomposer(params, options)
    secs, cpus, parts = [], [], []
    for img in frames:
        t0, c0 = time.perf_counter(), time.process_time()
        fr = video(img)
        secs.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        parts.append(fr)
    return secs, cpus, parts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="512x384", help="frame size WxH (default 512x384)")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each variant (median)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    frames = pan_frames((w, h), args.frames)
    params = Parameters()
    # warm-up: ONNX session, first-call allocations
    decompose(frames[0][None], params)
    variants = {
        "default (L2, warm start, last 2 alternations, Stage 0 reuse)": VideoOptions(),
        "default with the last 3 alternations": VideoOptions(later_iterations=3),
        "default without Stage 0 reuse": VideoOptions(reuse_features=False),
        "default with all 5 alternations": VideoOptions(later_iterations=0),
        "all 5 alternations, no Stage 0 reuse": VideoOptions(
            later_iterations=0, reuse_features=False
        ),
        "default with the L1 term": VideoOptions(temporal_norm="l1"),
        "frame by frame (VideoOptions.frame_by_frame)": VideoOptions.frame_by_frame(),
    }
    still, still_cpu = [], []
    for _ in range(args.repeats):
        for img in frames:
            t0, c0 = time.perf_counter(), time.process_time()
            decompose(img[None], params)
            still.append(time.perf_counter() - t0)
            still_cpu.append(time.process_time() - c0)
    still_mean = statistics.median(still)
    still_cpu_mean = statistics.median(still_cpu)
    print(
        f"{w}x{h}, {args.frames} frames, {torch.get_num_threads()} threads, "
        f"median of {args.repeats} runs"
    )
    print(
        f"still decompose (features included): {still_mean:.3f} s per frame (median), "
        f"{still_cpu_mean:.3f} s CPU"
    )
    print()
    print(
        "| variant | first frame s | later frames s (mean) | later / still | "
        "later / still, CPU time | reused |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    details = {}
    for name, opt in variants.items():
        firsts, laters, later_cpu, runs = [], [], [], []
        for _ in range(args.repeats):
            secs, cpus, parts = time_video(frames, params, opt)
            firsts.append(secs[0])
            laters.append(statistics.mean(secs[1:]))
            later_cpu.append(statistics.mean(cpus[1:]))
            runs.append(parts)
        first, later = statistics.median(firsts), statistics.median(laters)
        cpu = statistics.median(later_cpu)
        reused = sum(f.features_reused for f in runs[-1][1:])
        print(
            f"| {name} | {first:.3f} | {later:.3f} | {later / still_mean:.2f} | "
            f"{cpu / still_cpu_mean:.2f} | {reused}/{args.frames - 1} |"
        )
        keys = ("flow", "features", "decompose")
        details[name] = {
            k: statistics.mean(f.times.get(k, 0.0) for f in runs[-1][1:]) for k in keys
        }
    print()
    print("later frames, mean seconds per step (last run):")
    print("| variant | flow | Stage 0 (or its warp) | the method |")
    print("| --- | --- | --- | --- |")
    for name, d in details.items():
        print(f"| {name} | {d['flow']:.3f} | {d['features']:.3f} | {d['decompose']:.3f} |")


if __name__ == "__main__":
    main()
