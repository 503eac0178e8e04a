"""Start-up time of the ``torchiid`` command line: whole processes, median of N runs.

Each case is a fresh process of the installed console script (``torchiid`` next to this
Python, else ``python -m torchiid.cli``), timed from start to exit, so the figure is what a
user waits for: the interpreter, the imports and the work. The table also says whether the
process imported torch (``-X importtime`` of one extra run).

    python tools/bench_startup.py                 # --help, --version, decompose --help
    python tools/bench_startup.py --runs 9 --decompose   # and a small decompose run

``--decompose`` adds ``torchiid decompose`` of a 96x64 photo at one alternation (the compiled
kernels' cache loaded from disk, Stage 0, both stages, the files), after one untimed run that
fills numba's cache. Run it on an otherwise idle machine; it prints a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def command() -> list[str]:
    """The ``torchiid`` console script of this environment."""
    script = Path(sys.executable).parent / "torchiid"
    if script.exists():
        return [str(script)]
    found = shutil.which("torchiid")
    return [found] if found else [sys.executable, "-m", "torchiid.cli"]


def run_once(argv: list[str], env: dict[str, str]) -> tuple[float, int]:
    t0 = time.perf_counter()
    done = subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0, done.returncode


def imports_torch(args: list[str], env: dict[str, str]) -> bool:
    """Whether ``torchiid ARGS`` imports torch (one run under ``-X importtime``)."""
    code = "import sys; from torchiid.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", code, *args],
        env=env,
        capture_output=True,
        text=True,
    )
    return any(line.rpartition("|")[2].strip() == "torch" for line in done.stderr.splitlines())


def small_photo(folder: Path) -> Path:
    import cv2
    from skimage import data

    path = folder / "coffee.png"
    cv2.imwrite(str(path), cv2.resize(data.coffee()[..., ::-1], (96, 64)))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7, help="runs per case (median reported)")
    ap.add_argument("--decompose", action="store_true", help="also time a small decompose run")
    a = ap.parse_args()
    exe = command()
    env = dict(os.environ)
    cases: list[tuple[str, list[str]]] = [
        ("torchiid --help", ["--help"]),
        ("torchiid --version", ["--version"]),
        ("torchiid decompose --help", ["decompose", "--help"]),
    ]
    with tempfile.TemporaryDirectory() as tmp:
        if a.decompose:
            photo = small_photo(Path(tmp))
            args = [
                "decompose", str(photo), "-o", str(Path(tmp) / "out"), "--iterations", "1",
                "--no-progress", "--overwrite", "--redo",
            ]  # fmt: skip
            run_once(exe + args, env)  # fills numba's cache, exports the ONNX model
            cases.append(("torchiid decompose (96x64 px, 1 alternation)", args))
        print(f"{' '.join(exe)}; median of {a.runs} runs, each a fresh process\n")
        print("| command | median s | min s | max s | exit status | imports torch |")
        print("| --- | --- | --- | --- | --- | --- |")
        for name, args in cases:
            times, codes = [], set()
            for _ in range(a.runs):
                seconds, code = run_once(exe + args, env)
                times.append(seconds)
                codes.add(code)
            torch_loaded = "yes" if imports_torch(args, env) else "no"
            print(
                f"| `{name}` | {statistics.median(times):.3f} | {min(times):.3f} | "
                f"{max(times):.3f} | {','.join(map(str, sorted(codes)))} | {torch_loaded} |"
            )


if __name__ == "__main__":
    main()
