"""Score MIT-Berkeley from the files a user gets, not from tensors in memory.

Runs ``torchiid decompose --linear --mask OBJECT/mask.png`` on every object's ``diffuse.png``
(named ``OBJECT.png`` through a symbolic link in a scratch folder, so that the outputs carry
the object's name), then ``torchiid eval mit DIR --results OUT``, which reads the exact files
(``-reflectance-linear16.png`` and ``-shading.exr``).

    python tools/eval_mit_files.py ../shared/data/mit-berkeley -o eval-mit-files/
    python tools/eval_mit_files.py ../shared/data/mit-berkeley -o eval-mit-files/ -- --max-side 0
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="the MIT-Berkeley folder (one folder per object)")
    ap.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    ap.add_argument("extra", nargs="*", help="extra options for torchiid decompose (after --)")
    args = ap.parse_args()
    objects = sorted(p.name for p in args.root.iterdir() if (p / "diffuse.png").is_file())
    if not objects:
        raise SystemExit(f"{args.root}: no object folders with diffuse.png")
    layers = args.output / "layers"
    torchiid = [sys.executable, "-m", "torchiid.cli"]
    with tempfile.TemporaryDirectory() as tmp:
        for name in objects:
            link = Path(tmp) / f"{name}.png"
            link.symlink_to((args.root / name / "diffuse.png").resolve())
            cmd = [*torchiid, "decompose", str(link), "-o", str(layers), "--linear"]
            cmd += ["--mask", str(args.root / name / "mask.png"), "--overwrite", "--no-progress"]
            subprocess.run([*cmd, *args.extra], check=True)
    score = [*torchiid, "eval", "mit", str(args.root), "--results", str(layers)]
    score += ["-o", str(args.output / "scores"), "--overwrite", "--no-progress"]
    subprocess.run(score, check=True)


if __name__ == "__main__":
    main()
