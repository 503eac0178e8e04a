"""Seconds per step and peak memory of one preset on 512x341 photos, a batch of 1 and of 5.

Usage:
    python tools/bench_steps.py [--size 512] [--repeats 3] [--threads N] [--device cpu [cuda]]
        [--cli-repeats 3] [--preset default] [--iterations K] [--json results.json]

The photos are the five of ``tools/bench_bell.py`` (coffee, chelsea, astronaut, rocket and
the stereo motorcycle's left view from ``skimage.data``), centre-cropped to 3:2 and resized to
``--size`` px on the long side (512x341 by default), written as 8-bit sRGB PNGs into a
temporary folder. For each device and each batch (coffee alone; the five in one
``(5, 3, H, W)`` batch, solved together) a fresh worker process sets itself up as
``torchiid decompose`` does (threads, device, the ONNX feature extractor), runs once to warm
up and then ``--repeats`` times:

- decode: read each PNG from disk as the command does (``load_image`` and the file's SHA-256);
- the steps :func:`torchiid.model.decompose` times itself: CNN patch features, proposals
  (selective search), PCA / mid-level features, segments, shading solve 1..k, reflectance
  solve 1..k (with the preset's ``coarse_scale`` below 1, solves 1..k-1 run on the image at
  that scale); then the rest of its wall time (the working-resolution inputs, the coarse
  inputs and the full-resolution layers);
- outputs: every file the command writes for each photo (``write_outputs`` into an
  ``OutputSet``, put in place).

Printed: one Markdown table with a row per step (the median over the repeats, in seconds; a
batch of 5 per photo, i.e. divided by 5), the total, and the worker's peak memory (its
``ru_maxrss``, for the whole batch; on CUDA also ``torch.cuda.max_memory_allocated``). Then
the wall time of whole ``torchiid decompose`` processes into an empty folder (start-up
included; median of ``--cli-repeats``): one photo, and the five photos in one command, per
photo (the command takes them one at a time), with each process's peak RSS.

On CUDA the steps are timed at the pipeline's own synchronisation points (each solve reads
its residual back), and the whole decomposition is synchronised before it is timed. ``--device
cuda`` without a CUDA device stops with a one-line error.
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_bell import PHOTOS, make_photos  # noqa: E402

#: the Stage 0 steps :func:`torchiid.model.decompose` times, with the table's names
STAGE0 = {
    "patch features": "CNN patch features",
    "proposals": "proposals (selective search)",
    "mid-level g": "PCA / mid-level features",
    "segments": "segments (beyond the proposals, which they overlap)",
}
#: S_l's texture marks (made once at the working resolution when t_x is on)
MARKS = {"texture marks": "texture marks of S_l"}
REST = "inputs and full-resolution layers"
WORKER_RSS = "peak memory, worker RSS (GB)"
CUDA_PEAK = "peak CUDA memory allocated (GB)"
CLI_WALL = "`torchiid decompose` process, wall s per photo"
CLI_RSS = "`torchiid decompose` process, peak RSS (GB)"


def _one(decomposition, i: int):
    """Image ``i`` of a batch's decomposition, as a batch of one (what ``write_outputs`` takes)."""
    import dataclasses

    def take(x):
        return x if x is None else x[i : i + 1]

    names = ("reflectance", "shading", "sigma", "rho", "mask", "shading_white", "albedo_excess")
    return dataclasses.replace(decomposition, **{n: take(getattr(decomposition, n)) for n in names})


def _measure_once(paths, settings, state, phash) -> dict[str, float]:
    """One pass over ``paths`` as one batch: decode, decompose, outputs; seconds per step."""
    import torch

    from torchiid.collection import file_sha256
    from torchiid.collection.image_files import write_outputs
    from torchiid.io import load_image
    from torchiid.io.layers import OutputSet
    from torchiid.model import decompose

    def sync() -> None:
        if state.device.type == "cuda":
            torch.cuda.synchronize(state.device)

    t0 = time.perf_counter()
    loaded, hashes = [], []
    for p in paths:
        loaded.append(load_image(p))
        hashes.append(file_sha256(p))
    batch = torch.stack([item.image for item in loaded]).to(state.device)
    sync()
    t1 = time.perf_counter()
    out = decompose(batch, settings.params, return_stage1=True)
    sync()
    t2 = time.perf_counter()
    for i, item in enumerate(loaded):
        stem = Path(item.path).stem
        extra = {"input_sha256": hashes[i], "params_hash": phash}
        with OutputSet(settings.out, overwrite=True, label=stem) as tx:
            write_outputs(tx, stem, item, _one(out, i), settings, settings.params, t2 - t0, extra)
            tx.commit()
    t3 = time.perf_counter()
    steps = {"decode": t1 - t0}
    steps.update({k: out.times[k] for k in (*STAGE0, *MARKS) if k in out.times})
    steps.update({k: v for k, v in out.times.items() if k.startswith(("shading ", "reflectance "))})
    steps[REST] = (t2 - t1) - sum(v for k, v in steps.items() if k != "decode")
    steps["outputs"] = t3 - t2
    steps["total"] = t3 - t0
    return steps


def measure(
    paths: list[Path],
    out: Path,
    device: str,
    params,
    repeats: int,
    threads: int | None = None,
    warm_up: bool = True,
) -> dict:
    """Median seconds per step of ``paths`` as one batch, and this process's peak memory.

    Sets the process up as ``torchiid decompose`` does (one allocator arena,
    :func:`~torchiid.collection.worker_state`), warms up once (unless not ``warm_up``), then
    measures ``repeats`` passes. Returns
    ``{"steps": {name: seconds}, "rss_mb": ..., "batch": ..., "threads": ...}`` and, on CUDA,
    ``"cuda_mb"``.
    """
    import torch

    from torchiid.collection import RunSettings, params_hash, worker_state
    from torchiid.core.memory import share_one_malloc_arena

    share_one_malloc_arena()

    settings = RunSettings(
        out=out, params=params, device=device, overwrite=True, threads=threads or None
    )
    state = worker_state(settings)
    phash = params_hash(settings)
    if warm_up:  # kernels, allocator, caches
        _measure_once(paths, settings, state, phash)
    if state.device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(state.device)
    runs = [_measure_once(paths, settings, state, phash) for _ in range(repeats)]
    res = {
        "steps": {k: statistics.median(r[k] for r in runs) for k in runs[0]},
        "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6,  # KiB -> MB
        "batch": len(paths),
        "threads": torch.get_num_threads(),
    }
    if state.device.type == "cuda":
        res["cuda_mb"] = torch.cuda.max_memory_allocated(state.device) / 1e6
    return res


def _params(args: argparse.Namespace):
    from torchiid.params import Parameters

    params = Parameters.preset(args.preset)
    return params.replace(iterations=args.iterations) if args.iterations else params


def _worker(args: argparse.Namespace) -> None:
    paths = [Path(args.photos, f"{name}.png") for name in PHOTOS[: args.batch]]
    res = measure(paths, Path(args.out), args.device[0], _params(args), args.repeats, args.threads)
    print(json.dumps(res))


def _environment(threads: int | None) -> dict[str, str]:
    from torchiid.commands.common import THREAD_VARIABLES

    env = dict(os.environ)
    if threads:  # before torch loads in the child, as `torchiid decompose --threads` does
        env.update({name: str(threads) for name in THREAD_VARIABLES})
    return env


def _child(cmd: list[str], env: dict[str, str]) -> tuple[float, float, str]:
    """Run ``cmd``: its wall seconds, its own peak RSS (MB) and its output; exits on failure."""
    with tempfile.TemporaryFile("w+") as log:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, text=True)
        _, status, usage = os.wait4(proc.pid, 0)  # this child's rusage, not all children's
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        log.seek(0)
        text = log.read()
    if proc.returncode != 0:
        sys.stderr.write(text[-4000:])  # the child's traceback, above the one-line summary
        tail = text.strip().splitlines()[-1:] or ["(no output)"]
        raise SystemExit(f"bench_steps.py: {' '.join(cmd[:4])}... failed: {tail[0]}")
    return wall, usage.ru_maxrss * 1024 / 1e6, text


def run_worker(args: argparse.Namespace, photos: Path, device: str, batch: int) -> dict:
    """:func:`measure` in a fresh process (so that its peak memory is this batch's own)."""
    out = photos.parent / f"out-{device}-{batch}"
    cmd = [sys.executable, __file__, "--worker", "--photos", str(photos), "--out", str(out)]
    cmd += ["--batch", str(batch), "--device", device, "--repeats", str(args.repeats)]
    cmd += ["--preset", args.preset, "--iterations", str(args.iterations)]
    cmd += ["--threads", str(args.threads)] if args.threads else []
    _, _, text = _child(cmd, _environment(args.threads))
    return json.loads(text.strip().splitlines()[-1])


def run_cli(args: argparse.Namespace, photos: list[Path], device: str, work: Path) -> dict:
    """Whole ``torchiid decompose`` processes on ``photos``: median wall s per photo, peak RSS."""
    cmd = [sys.executable, "-m", "torchiid.cli", "decompose", *map(str, photos)]
    cmd += ["--no-progress", "-q", "--device", device, "--preset", args.preset]
    cmd += ["--iterations", str(args.iterations)] if args.iterations else []
    cmd += ["--threads", str(args.threads)] if args.threads else []
    walls, rss = [], []
    for _ in range(args.cli_repeats):
        out = work / "cli-out"
        shutil.rmtree(out, ignore_errors=True)  # an empty folder: nothing to skip
        wall, peak, _ = _child([*cmd, "-o", str(out)], _environment(None))
        walls.append(wall / len(photos))
        rss.append(peak)
    return {"seconds": statistics.median(walls), "rss_mb": max(rss), "runs": walls}


def _rows(k: int) -> list[str]:
    rows = ["decode", *STAGE0.values(), *MARKS.values()]
    rows += [f"shading solve {i}" for i in range(1, k + 1)]
    rows += [f"reflectance solve {i}" for i in range(1, k + 1)]
    return [*rows, REST, "outputs", "total"]


def _cells(res: dict, k: int) -> dict[str, str]:
    """The table's cells of one worker's result (seconds per photo)."""
    n, steps = res["batch"], res["steps"]
    named = {STAGE0.get(key, MARKS.get(key, key)): v for key, v in steps.items()}
    for i in range(1, k + 1):
        named[f"shading solve {i}"] = steps.get(f"shading {i}", float("nan"))
        named[f"reflectance solve {i}"] = steps.get(f"reflectance {i}", float("nan"))
    cells = {row: f"{named.get(row, float('nan')) / n:.3f}" for row in _rows(k)}
    cells["peak memory, worker RSS (GB)"] = f"{res['rss_mb'] / 1000:.2f}"
    if "cuda_mb" in res:
        cells["peak CUDA memory allocated (GB)"] = f"{res['cuda_mb'] / 1000:.2f}"
    return cells


def table(results: dict, k: int) -> str:
    """The Markdown table of ``results`` (``{(device, batch): worker result}``, CLI entries)."""
    columns = [key for key in results if key[0] != "cli"]
    cells = {key: _cells(results[key], k) for key in columns}
    for (device, batch), cli in ((key[1:], v) for key, v in results.items() if key[0] == "cli"):
        cell = cells.setdefault((device, batch), {})
        cell[CLI_WALL] = f"{cli['seconds']:.2f}"
        cell[CLI_RSS] = f"{cli['rss_mb'] / 1000:.2f}"
    columns = list(dict.fromkeys([*columns, *cells]))
    present = {row for key in columns for row in cells[key]}
    rows = [r for r in [*_rows(k), WORKER_RSS, CUDA_PEAK, CLI_WALL, CLI_RSS] if r in present]

    def title(device: str, batch: int) -> str:
        return f"{device}, batch of 1" if batch == 1 else f"{device}, batch of {batch} (per photo)"

    lines = ["| step | " + " | ".join(title(*key) for key in columns) + " |"]
    lines.append("| --- |" + " --- |" * len(columns))
    for row in rows:
        values = (cells[key].get(row, "") for key in columns)
        lines.append(f"| {row} | " + " | ".join(values) + " |")
    return "\n".join(lines)


def _check_devices(devices: list[str]) -> None:
    if "cuda" in devices:
        import torch

        if not torch.cuda.is_available():
            raise SystemExit("bench_steps.py: --device cuda: no CUDA device is available")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="long side of the 3:2 photos (px)")
    ap.add_argument("--repeats", type=int, default=3, help="measured passes per worker")
    ap.add_argument("--cli-repeats", type=int, default=3, help="runs of each process (0: none)")
    ap.add_argument("--device", nargs="+", default=["cpu"], choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=0, help="CPU threads (0: torchiid's default)")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 5], choices=range(1, 6))
    ap.add_argument("--preset", default="default", help="parameter preset")
    ap.add_argument("--iterations", type=int, default=0, help="alternations k (0: the preset's)")
    ap.add_argument("--json", type=Path, help="also write the measurements to this JSON file")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--photos", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--batch", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        _worker(args)
        return
    _check_devices(args.device)
    k = args.iterations or _params(args).iterations
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="bench-steps-") as tmp:
        work = Path(tmp)
        photos = make_photos(work / "photos", args.size, round(args.size * 2 / 3))
        h, w = round(args.size * 2 / 3), args.size
        results: dict = {}
        for device in args.device:
            for batch in args.batches:
                results[(device, batch)] = run_worker(args, work / "photos", device, batch)
            if args.cli_repeats > 0:
                for batch in args.batches:
                    results[("cli", device, batch)] = run_cli(args, photos[:batch], device, work)
    threads = next((r["threads"] for r in results.values() if "threads" in r), "?")
    print(
        f"`{args.preset}` preset, k = {k}, {w}x{h} photos, {threads} threads; seconds per photo "
        f"(median of {args.repeats} after a warm-up; the CLI rows: median of "
        f"{args.cli_repeats} processes); peak memory per process (a batch: the whole batch)"
    )
    print(table(results, k))
    print(f"load average before: {load}; after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if args.json is not None:
        flat = {" ".join(map(str, key)): value for key, value in results.items()}
        meta = {"size": [w, h], "preset": args.preset, "iterations": k, "threads": threads}
        args.json.write_text(json.dumps({"settings": meta, "results": flat}, indent=1) + "\n")


if __name__ == "__main__":
    main()
