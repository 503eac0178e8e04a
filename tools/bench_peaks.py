"""The two peaks of memory of ``torchiid decompose`` on one photo: Stage 0's CNN pass and after.

Usage:
    python tools/bench_peaks.py [--runs 5] [--size 512] [--against DIR] [--label-against 1.15.0]

A decomposition of one photo has two moments of high memory: Stage 0's CNN pass, whose
onnxruntime arena is handed back when the pass ends, and the last reflectance solve. The
process's peak RSS (what ``/usr/bin/time -v`` reports) is the larger of the two; this tool
shows both. It runs ``--runs`` whole ``torchiid decompose`` processes on coffee from
``skimage.data`` (3:2, ``--size`` px on the long side, as ``tools/bench_steps.py`` makes it)
and reads each one's resident memory (``VmRSS`` of ``/proc/PID/status``) every millisecond
from outside. The CNN pass is the part of the run up to the first fall of more than
``--drop`` MiB (100) once the memory has passed ``--floor`` MiB (400): the arena's hand-back;
the rest of the run is "after Stage 0". With ``--against DIR`` the processes of a second
checkout (run in ``DIR`` with ``PYTHONPATH=DIR``) run in turn with this one's, for a
side-by-side table. Linux
only. Printed: a Markdown table of medians (min–max) in MiB.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_bell import make_photos  # noqa: E402


def split_peaks(samples: list[float], floor: float, drop: float) -> tuple[float, float]:
    """``(peak up to the first fall of more than drop after passing floor, peak after it)``.

    ``nan`` for the second when no such fall happens (the whole run is then the first part).
    """
    if not samples:
        raise ValueError("no memory samples: the process ended before the first reading")
    top = 0.0
    for i, value in enumerate(samples):
        top = max(top, value)
        if top > floor and value < top - drop:
            return top, max(samples[i:])
    return max(samples), float("nan")


def _rss_mib(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None  # a zombie has no VmRSS line


def sample_run(
    cmd: list[str], env: dict[str, str] | None, cwd: Path | None = None, period: float = 0.001
) -> list[float]:
    """Run ``cmd`` in ``cwd``, reading its resident memory every ``period`` s; exit if it fails."""
    with tempfile.TemporaryFile("w+") as log:  # a file, not a pipe: a full pipe would block it
        proc = subprocess.Popen(
            cmd, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=log, text=True
        )
        samples = []
        while proc.poll() is None:
            value = _rss_mib(proc.pid)
            if value is not None:
                samples.append(value)
            time.sleep(period)
        log.seek(0)
        err = log.read()
    if proc.returncode != 0:
        tail = err.strip().splitlines()[-1:] or ["(no output)"]
        raise SystemExit(f"bench_peaks.py: {' '.join(cmd[:4])}... failed: {tail[0]}")
    return samples


def _cell(values: list[float]) -> str:
    seen = [v for v in values if not math.isnan(v)]
    if not seen:
        return "no hand-back seen"
    return f"{statistics.median(seen):.0f} ({min(seen):.0f}–{max(seen):.0f})"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="processes of each version")
    ap.add_argument("--size", type=int, default=512, help="long side of the 3:2 photo (px)")
    ap.add_argument("--against", type=Path, help="a second checkout, run in turn with this one")
    ap.add_argument("--label-against", default="other checkout", help="its column's title")
    ap.add_argument("--floor", type=float, default=400.0, help="MiB the CNN pass passes")
    ap.add_argument("--drop", type=float, default=100.0, help="MiB of the arena's hand-back")
    args = ap.parse_args(argv)
    if args.runs < 1:
        raise SystemExit("bench_peaks.py: --runs must be >= 1")
    if not Path("/proc/self/status").exists():
        raise SystemExit("bench_peaks.py: reads /proc/PID/status: Linux only")
    if args.against is not None and not (args.against / "torchiid").is_dir():
        raise SystemExit(f"bench_peaks.py: --against {args.against}: no torchiid package there")
    # each version's processes run in its own checkout: `python -m` puts the working folder
    # first on the path, before PYTHONPATH
    root = Path(__file__).resolve().parents[1]
    versions = {"this checkout": (dict(os.environ), root)}
    if args.against is not None:
        other = dict(os.environ, PYTHONPATH=str(args.against.resolve()))
        versions = {args.label_against: (other, args.against.resolve()), **versions}
    rows: dict[str, dict[str, list[float]]] = {v: {"cnn": [], "after": []} for v in versions}
    with tempfile.TemporaryDirectory(prefix="bench-peaks-") as tmp:
        work = Path(tmp)
        (photo, *_) = make_photos(work / "photos", args.size, round(args.size * 2 / 3))
        cmd = [sys.executable, "-m", "torchiid.cli", "decompose", str(photo), "-q"]
        for _ in range(args.runs):
            for name, (env, cwd) in versions.items():
                out = work / "out"
                shutil.rmtree(out, ignore_errors=True)
                samples = sample_run([*cmd, "-o", str(out)], env, cwd)
                cnn, after = split_peaks(samples, args.floor, args.drop)
                rows[name]["cnn"].append(cnn)
                rows[name]["after"].append(after)
    print(
        f"`torchiid decompose` on a {args.size}x{round(args.size * 2 / 3)} photo, resident "
        f"memory read every millisecond; medians (min–max) of {args.runs} processes, MiB"
    )
    print("| | " + " | ".join(versions) + " |")
    print("| --- |" + " --- |" * len(versions))
    for title, key in (
        ("during Stage 0's CNN pass", "cnn"),
        ("after Stage 0 (the solves)", "after"),
    ):
        print(f"| {title} | " + " | ".join(_cell(rows[v][key]) for v in rows) + " |")


if __name__ == "__main__":
    main()
