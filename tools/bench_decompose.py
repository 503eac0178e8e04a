"""Benchmark the full method (:func:`torchiid.model.decompose`) stage by stage.

Usage: python tools/bench_decompose.py [--sizes 256 512 1024] [--repeats 3] [--device cpu]
       [--threads N] [--iterations 5] [--image chelsea] [--preset default] [--params file.json]
       [--per-iteration]

For every size (the long side; 4:3 photos made by resizing a ``skimage.data`` image) the
decomposition runs ``--repeats`` times after one warm-up run, in a fresh subprocess per size
so that the peak memory is that size's own. Printed per size (medians over the repeats, in
seconds): the Stage 0 steps (patch features, proposals, mid-level features, segments), the
mean per-iteration shading and reflectance times, the first iteration's shading (cold, with
the coarse-to-fine start), the total wall time, its CPU time (``time.process_time``, robust
to other load on the machine) and the peak memory: CPU max RSS of the worker
(``resource.ru_maxrss``), and on CUDA ``torch.cuda.max_memory_allocated`` as well.
``--per-iteration`` adds one line per size with every alternation's shading and reflectance
time.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time


def _image(name: str, long_side: int):
    import numpy as np
    import torch
    from skimage import data, transform

    from torchiid.io import srgb_to_linear

    arr = getattr(data, name)()
    h, w = arr.shape[:2]
    # crop to 4:3 landscape, then resize
    if w * 3 > h * 4:
        cw = h * 4 // 3
        arr = arr[:, (w - cw) // 2 : (w - cw) // 2 + cw]
    else:
        ch = w * 3 // 4
        arr = arr[(h - ch) // 2 : (h - ch) // 2 + ch]
    out = transform.resize(arr, (long_side * 3 // 4, long_side), anti_aliasing=True)
    x = torch.from_numpy(np.ascontiguousarray(out, dtype=np.float32)).permute(2, 0, 1)
    return srgb_to_linear(x)[None]


def _worker(args: argparse.Namespace) -> None:
    import torch

    from torchiid.model import decompose
    from torchiid.params import Parameters

    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    x = _image(args.image, args.size).to(dev)
    base = Parameters.preset(args.preset)
    params = Parameters.from_json(args.params, base=base) if args.params else base
    # the method at the benchmark's size (tools/bench_photo_sizes.py measures the working
    # resolution path that photos take)
    params = params.replace(iterations=args.iterations, max_side=args.max_side)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    decompose(x, params)  # warm-up (model loading, allocator)
    sync()
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    runs = []
    for _ in range(args.repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        out = decompose(x, params)
        sync()
        t = dict(out.times)
        t["wall"] = time.perf_counter() - t0
        t["cpu"] = time.process_time() - c0
        runs.append(t)
    res = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    res["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6  # KiB -> MB
    if dev.type == "cuda":
        res["cuda_mb"] = torch.cuda.max_memory_allocated(dev) / 1e6
    res["threads"] = torch.get_num_threads()
    res["shape"] = list(x.shape[-2:])
    print(json.dumps(res))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--image", default="chelsea")
    ap.add_argument("--params", default="", help="JSON parameter file over the preset")
    ap.add_argument("--preset", default="default", help="parameter preset (default, paper)")
    ap.add_argument(
        "--max-side", type=int, default=0, help="working resolution (default 0: the size itself)"
    )
    ap.add_argument(
        "--per-iteration",
        action="store_true",
        help="also print every alternation's shading / reflectance seconds",
    )
    ap.add_argument("--size", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker(args)
        return
    k = args.iterations
    hdr = (
        f"{'size':>9} {'patch':>6} {'props':>6} {'mid':>5} {'segs':>5} {'sh 1':>5} "
        f"{'sh/it':>6} {'refl/it':>7} {'total':>6} {'cpu':>6} {'RSS MB':>7}"
    )
    print(
        f"decompose, k = {k}, device {args.device}, median of {args.repeats} "
        f"(+1 warm-up); seconds; sh/it, refl/it: mean over iterations (sh/it without the "
        f"first)"
    )
    print(hdr + (f" {'CUDA MB':>8}" if args.device.startswith("cuda") else ""))
    print("-" * len(hdr))
    for size in args.sizes:
        cmd = [
            sys.executable,
            __file__,
            "--worker",
            "--size",
            str(size),
            "--device",
            args.device,
            "--threads",
            str(args.threads),
            "--repeats",
            str(args.repeats),
            "--iterations",
            str(k),
            "--image",
            args.image,
            "--params",
            args.params,
            "--preset",
            args.preset,
            "--max-side",
            str(args.max_side),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(f"{size:>9} failed: {proc.stderr.strip().splitlines()[-1:]}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        sh = [r[f"shading {i}"] for i in range(2, k + 1)] or [r["shading 1"]]
        rf = [r[f"reflectance {i}"] for i in range(1, k + 1)]
        h, w = r["shape"]
        line = (
            f"{w:>4}x{h:<4} {r.get('patch features', 0):6.2f} {r.get('proposals', 0):6.2f} "
            f"{r.get('mid-level g', 0):5.2f} {r.get('segments', 0):5.2f} {r['shading 1']:5.2f} "
            f"{sum(sh) / len(sh):6.2f} {sum(rf) / len(rf):7.2f} {r['wall']:6.2f} "
            f"{r['cpu']:6.2f} {r['rss_mb']:7.0f}"
        )
        if "cuda_mb" in r:
            line += f" {r['cuda_mb']:8.0f}"
        print(line, flush=True)
        if args.per_iteration:
            its = "  ".join(
                f"{i}: {r[f'shading {i}']:.2f}/{r[f'reflectance {i}']:.2f}" for i in range(1, k + 1)
            )
            print(f"{'':>9} per alternation, shading/reflectance s: {its}", flush=True)
    print(
        f"threads {r['threads'] if 'r' in locals() else '?'}; peak RSS of each worker "
        f"process (includes the model and libraries)"
    )


if __name__ == "__main__":
    resource.getrusage(resource.RUSAGE_SELF)
    main()
