"""Seconds per photo of torchiid and of Bell et al. 2014's code, run alternately on the same photos.

Five photos shipped with scikit-image (coffee, chelsea, astronaut, rocket and the left view of
the stereo motorcycle), centre-cropped to 3:2 and resized to 512x341, saved as 8-bit sRGB PNGs.
Each pair of runs gives the same five files to

- torchiid: ``torchiid decompose PHOTOS -o OUT`` into an empty folder (default preset, as a
  user runs it: one process, start-up and every output file included), and
- Bell et al.: ``python tools/bell2014_port.py decompose PORT PHOTOS... -o OUT`` (their
  ``IntrinsicSolver`` with their default parameters, one process: imports, reading, the
  solves and two layers per photo written),

the first of the two alternating from pair to pair; ``--torchiid-threads N`` sets
``OMP_NUM_THREADS`` for torchiid's process (otherwise it uses every core). Per pair: each
process's wall seconds per photo (its wall time / 5), its CPU seconds per photo
(``RUSAGE_CHILDREN``, which other load on the machine inflates less) and the ratios
Bell / torchiid; then the medians over the pairs, and the per-photo times each process
reports for its own work (the seconds in torchiid's manifest, the solves of Bell's), with the load
average before each run.

    python tools/bell2014_port.py prepare SRC -o ../bell2014-py3
    nice -n 10 python tools/bench_bell.py --port ../bell2014-py3 [--pairs 3] [-o bench-bell/]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PHOTOS = ("coffee", "chelsea", "astronaut", "rocket", "motorcycle")


def make_photos(folder: Path, width: int = 512, height: int = 341) -> list[Path]:
    """The five photos, centre-cropped to ``width:height`` and resized, as sRGB PNGs."""
    import numpy as np
    from skimage import data, transform

    from torchiid.io import save_uint8

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in PHOTOS:
        arr = data.stereo_motorcycle()[0] if name == "motorcycle" else getattr(data, name)()
        h, w = arr.shape[:2]
        if w * height > h * width:
            cw = round(h * width / height)
            arr = arr[:, (w - cw) // 2 : (w - cw) // 2 + cw]
        else:
            ch = round(w * height / width)
            arr = arr[(h - ch) // 2 : (h - ch) // 2 + ch]
        out = transform.resize(arr, (height, width), anti_aliasing=True)
        paths.append(save_uint8(folder / f"{name}.png", np.round(out * 255).astype(np.uint8)))
    return paths


def _run(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float, str]:
    """Wall seconds, CPU seconds (user + system of the child) and stdout + stderr."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if run.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{run.stdout[-2000:]}{run.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, run.stdout + run.stderr


def run_torchiid(photos: list[Path], out: Path, extra: list[str], threads: int = 0) -> dict:
    """One ``torchiid decompose`` process on every photo (``threads``: ``OMP_NUM_THREADS``)."""
    cmd = [sys.executable, "-m", "torchiid.cli", "decompose", *map(str, photos), "-o", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)} if threads else None
    wall, cpu, _ = _run([*cmd, "--overwrite", "--no-progress", *extra], env)
    per = {}
    with open(out / "manifest.jsonl") as fh:  # one record per photo, with its seconds
        for line in fh:
            row = json.loads(line)
            if row.get("status") == "done":
                per[row["key"]] = row["seconds"]
    if len(per) != len(photos):
        raise SystemExit(f"{out}: torchiid decomposed {len(per)} of {len(photos)} photos")
    return {"wall": wall, "cpu": cpu, "per_photo": per}


def run_bell(port: Path, photos: list[Path], out: Path) -> dict:
    """One process running Bell et al.'s solver on every photo."""
    cmd = [sys.executable, str(HERE / "bell2014_port.py"), "decompose", str(port)]
    wall, cpu, text = _run([*cmd, *map(str, photos), "-o", str(out)])
    per = {}
    for line in text.splitlines():
        if line.startswith("{"):
            row = json.loads(line)
            per[Path(row["image"]).stem] = row["seconds"]
    return {"wall": wall, "cpu": cpu, "per_photo": per}


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", type=Path, required=True, help="a folder made by bell2014_port.py")
    ap.add_argument("--pairs", type=int, default=3, help="alternating pairs of runs")
    ap.add_argument("-o", "--output", type=Path, default=Path("bench-bell"))
    ap.add_argument("--size", default="512x341", help="WIDTHxHEIGHT of the photos")
    ap.add_argument("--photos", type=int, default=5, help="how many of the five photos")
    ap.add_argument(
        "--torchiid-threads", type=int, default=0, help="OMP_NUM_THREADS for torchiid (0: unset)"
    )
    ap.add_argument("torchiid_args", nargs="*", help="extra torchiid decompose options (after --)")
    args = ap.parse_args()
    if not (args.port / "PORTED.txt").is_file():
        raise SystemExit(f"{args.port}: not a port made by tools/bell2014_port.py prepare")
    width, height = (int(v) for v in args.size.lower().split("x"))
    photos = make_photos(args.output / "photos", width, height)[: args.photos]
    n = len(photos)
    rows = []
    for pair in range(args.pairs):
        order = ("torchiid", "bell") if pair % 2 == 0 else ("bell", "torchiid")
        row = {}
        for who in order:
            load = _load()
            # a fresh folder: torchiid skips the photos its manifest already records as done
            out = args.output / f"{who}-{pair + 1}"
            shutil.rmtree(out, ignore_errors=True)
            if who == "torchiid":
                row[who] = run_torchiid(photos, out, args.torchiid_args, args.torchiid_threads)
            else:
                row[who] = run_bell(args.port, photos, out)
            row[who]["load"] = load
            res = row[who]
            each = ", ".join(f"{k} {v:.1f}" for k, v in res["per_photo"].items())
            print(
                f"pair {pair + 1} {who}: {res['wall']:.1f} s wall, {res['cpu']:.1f} s CPU "
                f"for {n} photos ({each}; load average before: {load})",
                flush=True,
            )
        rows.append(row)
        (args.output / "runs.json").write_text(json.dumps(rows, indent=1))

    print(f"\nSeconds per photo, {n} photos of {width}x{height} per process")
    print("| pair | first | torchiid wall | Bell wall | ratio | torchiid CPU | Bell CPU | ratio |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    ratios, cpu_ratios = [], []
    for i, row in enumerate(rows):
        t, b = row["torchiid"], row["bell"]
        ratios.append(b["wall"] / t["wall"])
        cpu_ratios.append(b["cpu"] / t["cpu"])
        first = "torchiid" if i % 2 == 0 else "Bell"
        print(
            f"| {i + 1} | {first} | {t['wall'] / n:.2f} | {b['wall'] / n:.1f} | "
            f"{ratios[-1]:.1f}x | {t['cpu'] / n:.2f} | {b['cpu'] / n:.1f} | {cpu_ratios[-1]:.1f}x |"
        )

    def med(who: str, key: str) -> float:
        return statistics.median(r[who][key] for r in rows) / n

    print(
        f"| **median** | | **{med('torchiid', 'wall'):.2f}** | **{med('bell', 'wall'):.1f}** | "
        f"**{statistics.median(ratios):.1f}x** | {med('torchiid', 'cpu'):.2f} | "
        f"{med('bell', 'cpu'):.1f} | {statistics.median(cpu_ratios):.1f}x |"
    )
    print(f"\nPer photo, as each process reports its own work (median over the {len(rows)} pairs)")
    print("| photo | torchiid s | Bell s | ratio |")
    print("| --- | --- | --- | --- |")
    for path in photos:
        t = [r["torchiid"]["per_photo"].get(path.stem) for r in rows]
        b = [r["bell"]["per_photo"].get(path.stem) for r in rows]
        if None in t or None in b:
            continue
        tm, bm = statistics.median(t), statistics.median(b)
        print(f"| {path.stem} | {tm:.1f} | {bm:.1f} | {bm / tm:.1f}x |")
    print(f"\nload average at end: {_load()}")


if __name__ == "__main__":
    main()
