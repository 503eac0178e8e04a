"""Throughput of ``torchiid decompose`` over a collection, and the cost of a rerun's skip pass.

Part 1: ``--count`` photos of about 640x480 (crops of real photographs shipped with
scikit-image, flipped and shifted so that no two are the same, saved as JPEG quality 92) are
decomposed with the default settings, each configuration a fresh ``torchiid decompose`` process
into a fresh output folder, so the times include start-up, the workers' start-up and writing
every file:

* one process (torch's default threads: every core), the default;
* ``--workers 2`` (two worker processes of cores/2 threads);
* ``--workers 1 --threads N`` (one worker process with every core: the comparison of two
  1-thread workers against one 2-thread worker on 2 cores);
* ``--dask-scheduler`` on a local ``dask.distributed`` cluster of 2 worker processes of 1
  thread each (``distributed.LocalCluster``, the same as ``dask scheduler`` and two
  ``dask worker ... --nthreads 1``), started before the clock starts.

Part 2: ``--entries`` inputs (copies of one 640x480 JPEG under different names) with a manifest
that records every one of them as done, and their output files (empty) in place. Timed: a
rerun of ``torchiid decompose`` on them (a fresh process: start-up, listing, reading the
manifest, ``stat`` of every input, checking every output file, nothing to do), the skip pass
alone (in this process: listing + manifest + plan), and the same after every input was touched
(new modification time, same bytes: every input is hashed again and still skipped).

    python tools/bench_collection.py                              # 40 photos, 10,000 entries
    python tools/bench_collection.py --count 4 --entries 200 --fast   # a smoke test

Run it on an otherwise idle machine; it prints Markdown tables.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from skimage import data

from torchiid.collection import Manifest, RunSettings, params_hash, plan
from torchiid.collection.job import ImageResult, file_sha256
from torchiid.collection.manifest import MANIFEST_NAME, record_of
from torchiid.collection.pool import THREAD_VARIABLES, available_cores
from torchiid.io.inputs import list_inputs, unique_keys
from torchiid.io.layers import layer_file_names
from torchiid.params import Parameters

SOURCES = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "hubble_deep_field")


def make_photos(folder: Path, count: int, width: int, height: int) -> list[Path]:
    """``count`` distinct JPEG photos of ``width x height``."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(count):
        src = getattr(data, SOURCES[i % len(SOURCES)])()
        if src.ndim == 2:
            src = np.stack([src] * 3, axis=-1)
        h, w = src.shape[:2]
        scale = max(width / w, height / h) * (1.0 + 0.25 * rng.random())
        big = cv2.resize(src[..., :3], (int(w * scale) + 1, int(h * scale) + 1))
        y = int(rng.integers(0, big.shape[0] - height + 1))
        x = int(rng.integers(0, big.shape[1] - width + 1))
        img = big[y : y + height, x : x + width]
        if (i // len(SOURCES)) % 2:
            img = img[:, ::-1]
        path = folder / f"photo_{i:03d}.jpg"
        cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 92])
        paths.append(path)
    return paths


def run_cli(args: list[str], env: dict | None = None) -> tuple[float, str]:
    """Wall seconds and stderr of one ``torchiid`` process (``OMP_NUM_THREADS`` etc. unset)."""
    cmd = [sys.executable, "-m", "torchiid.cli", *args]
    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**clean, **(env or {})})
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr}")
    return seconds, proc.stderr


def throughput(args: argparse.Namespace, work: Path) -> list[tuple[str, int, float]]:
    photos = work / "photos"
    make_photos(photos, args.count, args.width, args.height)
    cores = available_cores()
    extra = ["--no-progress", *(["--iterations", "1", "--max-side", "128"] if args.fast else [])]
    configs = [
        ("1 process (default)", []),
        (f"--workers 2 ({max(1, cores // 2)} thread each)", ["--workers", "2"]),
        (f"--workers 1 --threads {cores}", ["--workers", "1", "--threads", str(cores)]),
    ]
    rows = []
    for name, options in configs:
        if args.only and not re.search(args.only, name, re.I):
            continue
        out = work / f"out-{len(rows)}"
        seconds, _ = run_cli(["decompose", str(photos), "-o", str(out), *options, *extra])
        rows.append((name, args.count, seconds))
        print(f"  {name}: {seconds:.1f} s", file=sys.stderr)
    if not args.only or re.search(args.only, "Dask LocalCluster", re.I):
        from distributed import LocalCluster

        with LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster:
            out = work / "out-dask"
            seconds, _ = run_cli(
                ["decompose", str(photos), "-o", str(out), "--dask-scheduler",
                 cluster.scheduler_address, *extra]
            )  # fmt: skip
        name = "Dask LocalCluster, 2 workers x 1 thread"
        rows.append((name, args.count, seconds))
        print(f"  {name}: {seconds:.1f} s", file=sys.stderr)
    return rows


def rerun_cost(args: argparse.Namespace, work: Path) -> list[tuple[str, int, float]]:
    src = work / "many"
    out = work / "out-many"
    src.mkdir()
    out.mkdir()
    sample = make_photos(work / "sample", 1, args.width, args.height)[0]
    raw = sample.read_bytes()
    settings = RunSettings(out=out, params=Parameters.preset("default"))
    phash = params_hash(settings)
    names = layer_file_names("x")
    t0 = time.perf_counter()
    with open(out / MANIFEST_NAME, "w", encoding="utf-8") as manifest:
        for i in range(args.entries):
            path = src / f"IMG_{i:05d}.jpg"
            path.write_bytes(raw)
            st = path.stat()
            files = [f"IMG_{i:05d}-{n[2:]}" for n in names]
            for name in files:
                (out / name).touch()
            result = ImageResult(i, path.stem, str(path), "done", files=files, seconds=1.0)
            result.sha256, result.size, result.mtime_ns = (
                file_sha256(path),
                st.st_size,
                st.st_mtime_ns,
            )
            manifest.write(json.dumps(record_of(result, phash)) + "\n")
    print(
        f"  made {args.entries} done entries in {time.perf_counter() - t0:.1f} s", file=sys.stderr
    )
    rows = []
    cli, err = run_cli(["decompose", str(src), "-o", str(out), "--no-progress"])
    assert f"0 done, {args.entries} skipped" in err, err
    rows.append(("rerun: `torchiid decompose` process, nothing to do", args.entries, cli))
    t0 = time.perf_counter()
    items = unique_keys(list_inputs([src]))
    decided = plan(items, Manifest(out / MANIFEST_NAME), phash, out=out)
    alone = time.perf_counter() - t0
    assert len(decided.done_before) == args.entries and decided.hashed == 0
    rows.append(("skip pass alone (list, read manifest, stat, check outputs)", args.entries, alone))
    for path in src.iterdir():
        os.utime(path)
    t0 = time.perf_counter()
    decided = plan(unique_keys(list_inputs([src])), Manifest(out / MANIFEST_NAME), phash, out=out)
    touched = time.perf_counter() - t0
    assert len(decided.done_before) == args.entries and decided.hashed == args.entries
    rows.append((f"skip pass after `touch` of every input ({len(raw) // 1000} kB each: all hashed)",
                 args.entries, touched))  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=40, help="photos for the throughput runs")
    parser.add_argument("--size", default="640x480", help="photo size WxH")
    parser.add_argument("--entries", type=int, default=10_000, help="done entries of the rerun")
    parser.add_argument("--only", help="regular expression: run only these configurations")
    parser.add_argument("--no-rerun", action="store_true", help="skip part 2")
    parser.add_argument("--no-throughput", action="store_true", help="skip part 1")
    parser.add_argument("--fast", action="store_true", help="1 iteration at 128 px (smoke test)")
    parser.add_argument("--work", type=Path, help="working folder (default: a temporary one)")
    args = parser.parse_args()
    args.width, args.height = (int(v) for v in args.size.lower().split("x"))
    work = Path(tempfile.mkdtemp(prefix="bench-collection-", dir=args.work))
    try:
        print(f"{available_cores()} cores; working in {work}", file=sys.stderr)
        if not args.no_throughput:
            rows = throughput(args, work)
            print(f"\n| configuration ({args.width}x{args.height} JPEG, default settings) "
                  "| images | seconds | images/minute |")  # fmt: skip
            print("| --- | --- | --- | --- |")
            for name, n, seconds in rows:
                print(f"| {name} | {n} | {seconds:.1f} | {60 * n / seconds:.1f} |")
        if not args.no_rerun:
            rows = rerun_cost(args, work)
            print("\n| rerun over done entries | entries | seconds |")
            print("| --- | --- | --- |")
            for name, n, seconds in rows:
                print(f"| {name} | {n} | {seconds:.2f} |")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
