"""Bell et al. 2014 (*Intrinsic Images in the Wild*) ported to Python 3 and run beside torchiid.

Bell, Bala and Snavely's published optimisation code (``bell2014/``, Python 2.7 with a Cython
wrapper around Krähenbühl and Koltun's dense CRF in C++) is the field's reference baseline.
None of it is part of torchiid: this tool takes a copy of their repository that the user has,
writes a Python 3 version of it into a folder of the user's choosing and builds its C++
extension with the local compiler (Cython from PyPI, Eigen from ``libeigen3-dev``). Nothing is
downloaded.

    python tools/bell2014_port.py prepare SRC -o PORT     # copy, rewrite, build
    python tools/bell2014_port.py decompose PORT photo.png ... -o OUT [--linear] [--mask M]

``SRC`` is an extracted copy of the repository (the folder holding ``bell2014/``) or its bare
git directory, whose ``HEAD`` is read file by file. ``decompose`` runs their
``IntrinsicSolver`` with ``IntrinsicParameters()`` (their defaults; ``fixed_seed`` on, so a
rerun gives the same layers, unless ``--random-seed``) and writes ``<stem>-reflectance.npy``
(float32 linear ``(H, W, 3)``) and ``<stem>-shading.npy`` (``(H, W)``), the exact files
``torchiid eval mit --results`` reads, and viewable sRGB PNGs of both. One JSON line per photo
gives the wall and CPU seconds of ``IntrinsicInput`` plus ``solve()``.

Input, as their ``decompose.py`` takes it: an 8-bit file is divided by 255 and decoded from
sRGB by their own ``srgb_to_rgb``; with ``--linear`` the file's values are used as linear
(MIT-Berkeley, as their ``IntrinsicInput.from_dataset("mit")``). Files are read through
:func:`torchiid.io.load_image`, which keeps a 16-bit file's precision where their loader
assumes 8 bits.

What the port changes, in every ``.py`` file (the rules of :func:`rewrite_python2`):

- ``print x`` statements become ``print(x)`` calls; ``xrange`` becomes ``range``;
  ``d.iteritems()`` (``iterkeys``, ``itervalues``) become ``items()`` (...); ``except E, e``
  becomes ``except E as e``; ``cPickle`` becomes ``pickle``.
- Implicit relative imports of a sibling module (``from judgements import ...``) become
  explicit (``from .judgements import ...``).
- The NumPy aliases that NumPy 1.24 removed become the types they stood for: ``np.float`` ->
  ``np.float64``, ``np.int`` -> ``np.int_``, ``np.bool`` -> ``np.bool_``.
- ``distutils`` (gone from Python 3.12) becomes ``setuptools``; ``scipy.ndimage.filters``
  becomes ``scipy.ndimage``.

Integer division needs no change: every ``/`` in their code has a float operand (their LMSE
already uses ``//``). The patches of :data:`PATCHES`, each applied exactly once or the port
stops, follow library changes and one data file the snapshot lacks:

- ``scipy.misc.imread``/``imsave`` (removed in SciPy 1.2) are read and written with Pillow;
  ``skimage.filter.denoise_bilateral`` is ``skimage.restoration``'s (``sigma_color``).
- ``skimage.morphology.label(labels, neighbors=4)`` is ``skimage.measure.label`` with
  ``connectivity=1`` on ``labels + 1`` with background 0, minus 1: connected components of
  equal labels, the masked pixels (label -1) kept at -1. Modern scikit-image treats the
  value 0 as background and numbers from 1, which would merge every region of label 0 and
  shift the numbering; the mapping that follows in ``split_label_clusters`` needs components
  numbered from 0 and the masked pixels at -1 (their logging mode asserts that the layers
  are unchanged by the split, and the port's test runs it).
- ``MiniBatchKMeans`` gets ``n_init=3, batch_size=100``, the defaults of scikit-learn 0.14
  that they used (scikit-learn 1.4 changed them to 1 and 1024).
- ``ProbAbsoluteReflectance`` loads ``prob_abs_r.dat`` only when ``abs_reflectance_weight``
  is nonzero: with their default weight 0 the density is never evaluated, and the file (and
  the ``bsdfs.csv`` it is made from) may be missing from a copy. With a
  nonzero weight the file is required as before (read with ``encoding="latin1"``, as Python 2
  pickles need); ``np.histogramdd(normed=)`` is ``density=``, and the histogram is indexed
  with a tuple.
- ``IntrinsicParameters.md5`` hashes the JSON's bytes; ``(int, long)`` is ``(int,)``.

The destination gets ``PORTED.txt``, the list of every change made to every file.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["PATCHES", "PortError", "apply_patches", "prepare", "rewrite_python2"]

PACKAGE = "bell2014"
EXTENSION = f"{PACKAGE}/krahenbuhl2013"
EIGEN = Path("/usr/include/eigen3/Eigen/Core")


class PortError(RuntimeError):
    """The source is not Bell et al.'s repository as this port knows it, or a build failed."""


# (what, pattern, replacement); applied line by line to every .py file
_LINE_RULES: list[tuple[str, re.Pattern[str], str]] = [
    ("print statement", re.compile(r"^(\s*)print\s*$"), r"\1print()"),
    ("xrange", re.compile(r"\bxrange\("), "range("),
    ("dict iterator", re.compile(r"\.iter(items|keys|values)\(\)"), r".\1()"),
    ("except E, e", re.compile(r"^(\s*except\s+[\w.()]+?),\s*(\w+)\s*:"), r"\1 as \2:"),
    ("cPickle", re.compile(r"\bcPickle\b"), "pickle"),
    ("np.float", re.compile(r"\bnp\.float\b(?![\w])"), "np.float64"),
    ("np.int", re.compile(r"\bnp\.int\b(?![\w])"), "np.int_"),
    ("np.bool", re.compile(r"\bnp\.bool\b(?![\w])"), "np.bool_"),
    (
        "distutils",
        re.compile(r"^from distutils\.(?:core|extension) import"),
        "from setuptools import",
    ),
    ("scipy.ndimage.filters", re.compile(r"\bscipy\.ndimage\.filters\b"), "scipy.ndimage"),
]
_PRINT = re.compile(r"^(\s*)print\s+(?![(\s=])(.*?)\s*$")
_FROM_IMPORT = re.compile(r"^(\s*)from\s+(\w+)\s+import\s")
_IMPORT = re.compile(r"^(\s*)import\s+(\w+)\s*$")


def _print_call(line: str) -> str | None:
    m = _PRINT.match(line)
    if m is None:
        return None
    indent, args = m.groups()
    if args.startswith(">>"):
        raise PortError(f"print >> redirection is not supported: {line.strip()!r}")
    if args.endswith(","):
        return f"{indent}print({args[:-1].rstrip()}, end=' ')"
    return f"{indent}print({args})"


def rewrite_python2(text: str, siblings: frozenset[str] = frozenset()) -> tuple[str, list[str]]:
    """Rewrite the Python-2-only constructs of one module (see the module docstring).

    Args:
        text: the module's source.
        siblings: names of the modules and packages beside it in its package, whose implicit
            relative imports become explicit.

    Returns:
        The rewritten source and one note per changed line (``"line N: what"``).
    """
    out, notes = [], []
    for number, line in enumerate(text.split("\n"), 1):
        new, what = line, []
        call = _print_call(new)
        if call is not None:
            new, what = call, ["print statement"]
        for name, pattern, repl in _LINE_RULES:
            changed = pattern.sub(repl, new)
            if changed != new:
                new = changed
                what.append(name)
        for pattern, repl in (
            (_FROM_IMPORT, r"\1from .\2 import "),
            (_IMPORT, r"\1from . import \2"),
        ):
            m = pattern.match(new)
            if m and m.group(2) in siblings:
                new = pattern.sub(repl, new, count=1)
                what.append("implicit relative import")
        if what:
            notes.append(f"line {number}: {', '.join(dict.fromkeys(what))}")
        out.append(new)
    return "\n".join(out), notes


#: file -> [(old, new, why)]: each ``old`` must occur exactly once (after rewrite_python2)
PATCHES: dict[str, list[tuple[str, str, str]]] = {
    f"{PACKAGE}/image_util.py": [
        (
            "from scipy.misc import imread, imsave\n",
            "from PIL import Image as _Image\n\n\n"
            "def imread(filename):\n    return np.asarray(_Image.open(filename))\n\n\n"
            "def imsave(filename, image):\n    _Image.fromarray(image).save(filename)\n\n\n",
            "scipy.misc.imread/imsave were removed from SciPy; Pillow reads and writes",
        ),
        (
            "from skimage.filter import denoise_bilateral",
            "from skimage.restoration import denoise_bilateral",
            "skimage.filter is skimage.restoration",
        ),
        ("sigma_range=sigma_range,", "sigma_color=sigma_range,", "denoise_bilateral's keyword"),
    ],
    f"{PACKAGE}/solver.py": [
        (
            "from skimage import morphology\n",
            "from skimage import measure\n",
            "connected components come from skimage.measure",
        ),
        (
            "morphology.label(labels, neighbors=neighbors)",
            "measure.label(labels + 1, background=0, connectivity=1 if neighbors == 4 else 2) - 1",
            "components numbered from 0, masked pixels (-1) kept at -1, label 0 not background",
        ),
        (
            "compute_labels=False, random_state=random_state)",
            "compute_labels=False, random_state=random_state, n_init=3, batch_size=100)",
            "scikit-learn 0.14's MiniBatchKMeans defaults",
        ),
    ],
    f"{PACKAGE}/energy/prob_abs_r.py": [
        (
            "        self._load()\n",
            "        if params.abs_reflectance_weight:\n            self._load()\n",
            "the density is used only with a nonzero weight (default 0)",
        ),
        (
            "'bsdfs.csv'), 'rb')",
            "'bsdfs.csv'), 'r', newline='')",
            "the csv module reads text in Python 3",
        ),
        (
            'gzip.open(data_filename, "rb"))',
            'gzip.open(data_filename, "rb"), encoding="latin1")',
            "a Python 2 pickle with NumPy arrays",
        ),
    ],
    f"{PACKAGE}/density.py": [
        ("normed=True", "density=True", "np.histogramdd's keyword"),
        ("self.hist[indices]", "self.hist[tuple(indices)]", "NumPy indexes with a tuple"),
    ],
    f"{PACKAGE}/params.py": [
        ("m.update(dump)", "m.update(dump.encode())", "hashlib takes bytes"),
        ("if t in (int, long):", "if t in (int,):", "Python 3 has one integer type"),
    ],
}


def apply_patches(
    text: str, patches: list[tuple[str, str, str]], name: str
) -> tuple[str, list[str]]:
    """Apply ``(old, new, why)`` replacements, each of which must match exactly once.

    Raises:
        PortError: an ``old`` text occurs zero or several times in ``text``.
    """
    notes = []
    for old, new, why in patches:
        count = text.count(old)
        if count != 1:
            raise PortError(f"{name}: expected {old.strip()!r} once, found it {count} times")
        text = text.replace(old, new)
        notes.append(f"patch: {why}")
    return text, notes


def _read_source(src: Path) -> dict[str, bytes]:
    """Every file of the repository: from a folder, or from a bare git directory's HEAD."""
    if (src / PACKAGE).is_dir():
        return {
            p.relative_to(src).as_posix(): p.read_bytes()
            for p in sorted(src.rglob("*"))
            if p.is_file() and ".git" not in p.relative_to(src).parts
        }
    if (src / "HEAD").is_file() and (src / "objects").is_dir():
        git = ["git", f"--git-dir={src}"]
        listing = subprocess.run(
            [*git, "ls-tree", "-r", "-z", "HEAD"], capture_output=True, check=True
        ).stdout.decode()
        files = {}
        for entry in filter(None, listing.split("\0")):
            meta, path = entry.split("\t", 1)
            sha = meta.split()[2]
            blob = subprocess.run([*git, "cat-file", "blob", sha], capture_output=True)
            if blob.returncode == 0:  # a snapshot may lack its largest files
                files[path] = blob.stdout
        return files
    raise PortError(
        f"{src}: neither a copy of Bell et al.'s repository (no {PACKAGE}/) nor its git dir"
    )


def _siblings(rel: str, files: dict[str, bytes]) -> frozenset[str]:
    """The modules and subpackages beside ``rel`` in its package (none outside a package)."""
    folder = Path(rel).parent
    if f"{folder.as_posix()}/__init__.py" not in files:
        return frozenset()
    names = set()
    for other in map(Path, files):
        if other.parent == folder and other.suffix == ".py":
            names.add(other.stem)
        elif other.parent.parent == folder and other.name == "__init__.py":
            names.add(other.parent.name)
    return frozenset(names - {"__init__"})


def prepare(src: str | Path, dst: str | Path, build: bool = True) -> list[str]:
    """Write the Python 3 port of ``src`` into ``dst`` and build its C++ extension.

    Args:
        src: an extracted copy of the repository, or its bare git directory.
        dst: the destination folder (created; an existing port there is replaced).
        build: also compile ``krahenbuhl2013`` in place and import it.

    Returns:
        The notes written to ``dst/PORTED.txt``.

    Raises:
        PortError: the source is not the expected repository, or the build failed.
    """
    src, dst = Path(src), Path(dst)
    files = _read_source(src)
    missing = sorted({f"{PACKAGE}/solver.py", *PATCHES} - set(files))
    if missing:
        raise PortError(f"{src}: missing {', '.join(missing)}")
    if dst.exists():
        if not (dst / "PORTED.txt").is_file():
            raise PortError(f"{dst} exists and is not a port made by this tool")
        shutil.rmtree(dst)
    notes = []
    for rel, data in files.items():
        path = dst / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        if rel.endswith(".py"):
            text, changed = rewrite_python2(data.decode("utf-8"), _siblings(rel, files))
            text, patched = apply_patches(text, PATCHES.get(rel, []), rel)
            compile(text, rel, "exec")
            notes += [f"{rel}: {n}" for n in changed + patched]
            path.write_text(text, encoding="utf-8")
        else:
            path.write_bytes(data)
    (dst / "PORTED.txt").write_text(
        f"Python 3 port of {src} made by tools/bell2014_port.py\n\n" + "\n".join(notes) + "\n"
    )
    if build:
        _build(dst / EXTENSION)
    return notes


def _build(folder: Path) -> None:
    if not EIGEN.is_file():
        raise PortError(f"Eigen headers not found ({EIGEN}): apt-get install libeigen3-dev")
    run = subprocess.run(
        [sys.executable, "setup.py", "build_ext", "--inplace"],
        cwd=folder,
        capture_output=True,
        text=True,
    )
    if run.returncode != 0:
        raise PortError(f"building {folder} failed:\n{run.stdout[-3000:]}{run.stderr[-3000:]}")
    check = subprocess.run(
        [sys.executable, "-c", f"import {PACKAGE}.krahenbuhl2013.krahenbuhl2013"],
        cwd=folder.parents[1],
        capture_output=True,
        text=True,
    )
    if check.returncode != 0:
        raise PortError(f"the built extension does not import: {check.stderr.strip()[-500:]}")


def load(port: str | Path):
    """Import the port's ``bell2014`` package (``prepare`` first); returns the package."""
    port = Path(port).resolve()
    if not (port / "PORTED.txt").is_file():
        raise PortError(
            f"{port}: not a port (run: python tools/bell2014_port.py prepare SRC -o {port})"
        )
    if str(port) not in sys.path:
        sys.path.insert(0, str(port))
    import importlib

    try:
        for name in ("solver", "input", "params", "image_util"):
            importlib.import_module(f"{PACKAGE}.{name}")
    except ImportError as exc:
        raise PortError(f"{port}: {exc} (was the extension built?)") from None
    return sys.modules[PACKAGE]


def solve(bell, image, mask=None, fixed_seed: bool = True):
    """Their decomposition of a **linear** ``(H, W, 3)`` float image, default parameters.

    Returns:
        ``(reflectance (H, W, 3), shading (H, W), times)``, the layers linear and zero outside
        ``mask``; ``times``: wall ``seconds`` and ``cpu_seconds`` (this process's CPU time,
        which other load on the machine inflates less).
    """
    import numpy as np

    t0, c0 = time.perf_counter(), time.process_time()
    params = bell.params.IntrinsicParameters()
    params.fixed_seed = fixed_seed
    inp = bell.input.IntrinsicInput(np.asarray(image, dtype=np.float64), mask=mask)
    r, s, _ = bell.solver.IntrinsicSolver(inp, params).solve()
    cpu = time.process_time() - c0
    return r, s, {"seconds": round(time.perf_counter() - t0, 3), "cpu_seconds": round(cpu, 3)}


def read_input(bell, path: Path, linear: bool):
    """The file as their ``decompose.py`` takes it: sRGB decoded by their code, or as linear."""
    import numpy as np

    from torchiid.io import load_image

    values = load_image(path, linear=True, alpha="ignore", min_side=1).image
    image = values.permute(1, 2, 0).numpy().astype(np.float64)
    return image if linear else bell.image_util.srgb_to_rgb(image)


def write_layers(out: Path, stem: str, r, s) -> None:
    """``<stem>-reflectance.npy``/``-shading.npy`` (exact) and viewable sRGB PNGs of both."""
    import numpy as np

    from torchiid.io import save_image

    for layer, arr in (("reflectance", r), ("shading", s)):
        arr = np.asarray(arr, dtype=np.float32)
        save_image(out / f"{stem}-{layer}.npy", arr, encoding="npy")
        top = float(np.percentile(arr[arr > 0], 99.9)) if (arr > 0).any() else 1.0
        save_image(out / f"{stem}-{layer}.png", arr / max(top, 1e-12), encoding="srgb8")


def _decompose(args: argparse.Namespace) -> None:
    from torchiid.io import load_mask

    bell = load(args.port)
    if args.mask and len(args.images) != 1:
        raise SystemExit("--mask needs exactly one image")
    args.output.mkdir(parents=True, exist_ok=True)
    for path in args.images:
        image = read_input(bell, path, args.linear)
        mask = load_mask(args.mask, shape=image.shape[:2])[0].numpy() if args.mask else None
        r, s, times = solve(bell, image, mask, fixed_seed=not args.random_seed)
        write_layers(args.output, path.stem, r, s)
        print(json.dumps({"image": str(path), **times}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("prepare", help="write the Python 3 port and build its extension")
    p.add_argument("source", type=Path, help="a copy of the repository, or its bare git dir")
    p.add_argument("-o", "--output", type=Path, required=True, help="the port's folder")
    p.add_argument("--no-build", action="store_true", help="rewrite only")
    d = sub.add_parser("decompose", help="run their solver on photos")
    d.add_argument("port", type=Path, help="a folder made by 'prepare'")
    d.add_argument("images", type=Path, nargs="+")
    d.add_argument("-o", "--output", type=Path, required=True)
    d.add_argument("--linear", action="store_true", help="the files hold linear values")
    d.add_argument("--mask", type=Path, help="mask file (one image only)")
    d.add_argument("--random-seed", action="store_true", help="unseeded k-means (their default)")
    args = ap.parse_args()
    try:
        if args.command == "prepare":
            notes = prepare(args.source, args.output, build=not args.no_build)
            print(f"{args.output}: {len(notes)} changes (see PORTED.txt)")
        else:
            _decompose(args)
    except PortError as exc:
        raise SystemExit(f"bell2014_port: error: {exc}") from None


if __name__ == "__main__":
    main()
