"""Score Bell et al. 2014 on MIT-Berkeley with the LMSE that scores torchiid.

Runs their solver (the Python 3 port of ``tools/bell2014_port.py``, default parameters) on every
object's ``diffuse.png`` under ``mask.png``, writes ``<object>-reflectance.npy`` and
``<object>-shading.npy`` (float32 linear) into ``OUT/layers`` and scores that folder with
``torchiid eval mit ROOT --results OUT/layers`` (scores in ``OUT/scores``), the command that
scores torchiid's own files (``tools/eval_mit_files.py``). Prints one line per object (LMSE and
the wall and CPU seconds of their ``IntrinsicInput`` and ``solve()``) and the means, with the
load average.

The input is the same file torchiid reads, taken as each method expects a linear 16-bit PNG:
divided by 65535 and used as linear (their ``IntrinsicInput.from_dataset("mit")`` protocol,
at 16 bits where their own loader reads 8), the mask read by torchiid's ``load_mask``.

    python tools/bell2014_port.py prepare SRC -o ../bell2014-py3
    nice -n 10 python tools/eval_mit_bell.py ../shared/data/mit-berkeley --port ../bell2014-py3 \
        -o eval-mit-bell/

Objects whose two ``.npy`` files and seconds (``OUT/seconds.json``) already exist are not run
again; ``--overwrite`` runs them all.
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _port_tool():
    spec = importlib.util.spec_from_file_location("bell2014_port", HERE / "bell2014_port.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="the MIT-Berkeley folder (one folder per object)")
    ap.add_argument("--port", type=Path, required=True, help="a folder made by bell2014_port.py")
    ap.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    ap.add_argument("--objects", nargs="+", help="only these objects")
    ap.add_argument("--random-seed", action="store_true", help="unseeded k-means (their default)")
    ap.add_argument("--overwrite", action="store_true", help="run every object again")
    args = ap.parse_args()

    from torchiid.io import load_mask

    tool = _port_tool()
    try:
        bell = tool.load(args.port)
    except tool.PortError as exc:
        raise SystemExit(f"eval_mit_bell: error: {exc}") from None
    objects = args.objects or sorted(
        p.name for p in args.root.iterdir() if (p / "diffuse.png").is_file()
    )
    if not objects:
        raise SystemExit(f"{args.root}: no object folders with diffuse.png")
    layers = args.output / "layers"
    layers.mkdir(parents=True, exist_ok=True)
    seconds_path = args.output / "seconds.json"
    seconds = (
        {} if args.overwrite or not seconds_path.is_file() else json.loads(seconds_path.read_text())
    )
    print(f"load average at start: {_load()}", flush=True)
    for name in objects:
        done = all(
            (layers / f"{name}-{layer}.npy").is_file() for layer in ("reflectance", "shading")
        )
        if done and name in seconds:
            continue
        folder = args.root / name
        image = tool.read_input(bell, folder / "diffuse.png", linear=True)
        mask = load_mask(folder / "mask.png", shape=image.shape[:2])[0].numpy()
        r, s, times = tool.solve(bell, image, mask, fixed_seed=not args.random_seed)
        tool.write_layers(layers, name, r, s)
        seconds[name] = times
        seconds_path.write_text(json.dumps(seconds, indent=1))
        took, cpu = times["seconds"], times["cpu_seconds"]
        print(f"{name}: {took:.1f} s, CPU {cpu:.1f} s (load average {_load()})", flush=True)
    score = [sys.executable, "-m", "torchiid.cli", "eval", "mit", str(args.root)]
    score += ["--results", str(layers), "-o", str(args.output / "scores")]
    score += ["--overwrite", "--no-progress"]
    if args.objects:
        ids = args.output / "ids.txt"
        ids.write_text("\n".join(objects) + "\n")
        score += ["--ids", str(ids)]
    subprocess.run(score, check=True, stdout=subprocess.DEVNULL)
    with open(args.output / "scores" / "results.csv", newline="") as fh:
        rows = {row["id"]: row for row in csv.DictReader(fh)}
    metrics = [k for k in next(iter(rows.values())) if k not in ("id", "seconds")]
    print(f"\n| object | {' | '.join(metrics)} | seconds | CPU seconds |")
    print("|" + " --- |" * (len(metrics) + 3))
    for name in objects:
        vals = " | ".join(f"{float(rows[name][m]):.5f}" for m in metrics)
        times = seconds[name]
        print(f"| {name} | {vals} | {times['seconds']:.1f} | {times['cpu_seconds']:.1f} |")
    means = " | ".join(
        f"**{statistics.mean(float(rows[n][m]) for n in objects):.5f}**" for m in metrics
    )
    med = [statistics.median(seconds[n][k] for n in objects) for k in ("seconds", "cpu_seconds")]
    print(f"| **mean** (seconds: median) | {means} | {med[0]:.1f} | {med[1]:.1f} |")
    print(f"\nload average at end: {_load()}")


if __name__ == "__main__":
    main()
