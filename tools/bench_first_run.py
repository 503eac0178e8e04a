"""A first run's wait: ``torchiid decompose`` with numba's cache empty, with and without the helper.

Each run is a fresh ``torchiid decompose PHOTO -o OUT -q`` process with ``NUMBA_CACHE_DIR``
set to a new empty folder, so numba compiles every kernel as in a new Python environment. The
runs alternate ``TORCHIID_COMPILE_AHEAD=0`` (the run compiles every kernel itself) and ``=1``
(a second process compiles Stage 2's kernels meanwhile, :mod:`torchiid.pipeline.compile_ahead`),
``--pairs`` times. Printed: a Markdown table with the median (and range) of the wall seconds,
of the CPU seconds of the process and its children (the helper among them), and of the peak
memory of the ``torchiid`` process itself, then the paired ratios of the wall times.

    python tools/bench_first_run.py [--pairs 3] [--photo coffee.png] [--threads N]

The photo defaults to ``skimage.data``'s coffee (600×400, worked at 512×341). Run it on an
otherwise idle machine: compilation is single-threaded, and the helper takes another core.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_startup import command  # noqa: E402


def coffee(folder: Path) -> Path:
    import cv2
    from skimage import data

    path = folder / "coffee.png"
    cv2.imwrite(str(path), data.coffee()[..., ::-1])
    return path


def first_run(argv: list[str], env: dict[str, str], log: Path) -> tuple[float, float, float]:
    """Wall seconds, CPU seconds (with children) and the process's peak RSS in MiB."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with log.open("wb") as err:
        proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    if proc.returncode != 0:
        raise SystemExit(f"the run failed ({proc.returncode}): {log.read_text().strip()}")
    # the helper is the run's child, reaped by the run: counted in the run's children
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, usage.ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=3, help="runs of each case, alternating")
    ap.add_argument("--photo", type=Path, help="the photo (default: skimage.data's coffee)")
    ap.add_argument("--threads", type=int, default=0, help="--threads of the runs (0: default)")
    a = ap.parse_args()
    exe = command()
    results: dict[str, list[tuple[float, float, float]]] = {"0": [], "1": []}
    with tempfile.TemporaryDirectory() as tmp:
        photo = a.photo or coffee(Path(tmp))
        for i in range(a.pairs):
            for ahead in ("0", "1"):
                run = Path(tmp, f"run-{i}-{ahead}")
                env = {
                    **os.environ,
                    "NUMBA_CACHE_DIR": str(run / "numba"),
                    "TORCHIID_COMPILE_AHEAD": ahead,
                }
                argv = [*exe, "decompose", str(photo), "-o", str(run / "out"), "-q"]
                if a.threads:
                    argv += ["--threads", str(a.threads)]
                results[ahead].append(first_run(argv, env, run.with_suffix(".log")))
                wall = results[ahead][-1][0]
                print(f"pair {i + 1}, helper {ahead}: {wall:.1f} s", file=sys.stderr)
    print(f"`torchiid decompose {photo.name} -o OUT -q`, numba's cache empty; {a.pairs} runs "
          "of each, alternating\n")  # fmt: skip
    print("| | wall s, median (range) | CPU s with children | peak MiB of the process |")
    print("| --- | --- | --- | --- |")
    for ahead, name in (("0", "one process (`TORCHIID_COMPILE_AHEAD=0`)"),
                        ("1", "with the second process (the default)")):  # fmt: skip
        cols = []
        for j in range(3):
            xs = [r[j] for r in results[ahead]]
            cols.append(f"{statistics.median(xs):.1f} ({min(xs):.1f}–{max(xs):.1f})")
        print(f"| {name} | {' | '.join(cols)} |")
    ratios = [b[0] / a0[0] for a0, b in zip(results["0"], results["1"], strict=True)]
    print(f"\npaired wall ratio (helper / one process): median {statistics.median(ratios):.2f} "
          f"({min(ratios):.2f}–{max(ratios):.2f})")  # fmt: skip


if __name__ == "__main__":
    main()
