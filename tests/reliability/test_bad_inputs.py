"""The bad-input suite: the installed command, end to end, on bad and unusual inputs.

For every case: the exit status; one line that names the file and the problem; no traceback;
nothing partial and no temporary (dot) file left in the output folder; old outputs byte for
byte as they were. To stay fast (tiny images, ``--iterations 1``), the inputs that are handled
one by one run as a few batches of ``python -m torchiid.cli decompose`` (one process each), and
the usage and set-up errors, which all end before any decomposition, run in one process that
forks a child per command line (``reliability_harness.run_many``).

Interrupts are made deterministic in two ways. While files are written or renamed, the
test-only hook ``TORCHIID_TEST_INTERRUPT=write:N`` / ``commit:N`` raises a real SIGINT in the
process at that point (sending a signal from outside could not hit a window of a few
milliseconds reliably). During a computation, the test sends SIGINT from outside once the
first image of the batch is reported done: the second image takes seconds to decompose, so
the signal lands in its computation.
"""

from __future__ import annotations

import fcntl
import json
import os
import pty
import signal
import struct
import subprocess
import sys
import tempfile
import termios
from pathlib import Path

import cv2
import numpy as np
import pytest
from reliability_harness import ENV, run_cli, run_many
from skimage import data

from torchiid.io import layer_file_names, save_image
from torchiid.params import Parameters

FAST = ["--iterations", "1"]
W, H = 80, 64


def _photo(w: int = W, h: int = H) -> np.ndarray:
    """An (h, w, 3) uint8 BGR photo."""
    return cv2.resize(data.chelsea(), (w, h), interpolation=cv2.INTER_AREA)[..., ::-1].copy()


def _encode(ext: str, img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


def _write(path: Path, payload) -> None:
    if isinstance(payload, bytes):
        path.write_bytes(payload)
    elif isinstance(payload, str):
        path.write_text(payload)
    elif isinstance(payload, np.ndarray) and path.suffix == ".npy":
        np.save(path, payload, allow_pickle=payload.dtype == object)
    else:
        assert cv2.imwrite(str(path), payload)


def _flip(raw: bytes, at: int) -> bytes:
    b = bytearray(raw)
    b[at] ^= 0xFF
    return bytes(b)


def _png_idat_offset(raw: bytes) -> int:
    return raw.index(b"IDAT") + 20


def _exr_bytes(tmp: Path) -> bytes:
    save_image(tmp, np.full((H, W, 3), 0.5, np.float32), "exr")
    raw = tmp.read_bytes()
    tmp.unlink()
    return raw


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def _hidden(folder: Path) -> list[str]:
    """Dot files and folders, and names of temporary files, anywhere below ``folder``."""
    if not folder.exists():
        return []
    return [
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.name.startswith(".") or p.suffix in (".tmp", ".partial")
    ]


def _set_names(stem: str) -> set[str]:
    return set(layer_file_names(stem)) | {f"{stem}-sigma.exr"}


def _assert_clean(run) -> None:
    text = run.stdout + run.stderr
    assert "Traceback" not in text, text
    # no decoder chatter (OpenCV's log, libjpeg, libpng) beside torchiid's own lines
    others = "\n".join(x for x in text.splitlines() if "torchiid: error:" not in x)
    for noise in ("[ERROR", "[ WARN", "Corrupt JPEG", "libpng", "Premature end"):
        assert noise not in others, text
    assert all(line.isprintable() for line in run.lines), run.lines


# ------------------------------------------------------------------------------------------
# Batch A: one `torchiid decompose` over bad and good files, progress bar on


def _batch_a_inputs(tmp: Path) -> dict[str, object]:
    """File name -> content for batch A (bytes, text, an image array or a .npy array)."""
    bgr = _photo()
    png, jpg = _encode(".png", bgr), _encode(".jpg", bgr)
    tif, webp = _encode(".tif", bgr), _encode(".webp", bgr)
    rgba = np.dstack([bgr, np.full((H, W), 255, np.uint8)])
    holes = rgba.copy()
    holes[:, : W // 2, 3] = 0
    clear = rgba.copy()
    clear[..., 3] = 0
    lin = bgr[..., ::-1].astype(np.float32) / 255
    nan, inf = lin.copy(), lin.copy()
    nan[3, 3, 1] = np.nan
    inf[5, 5, 0] = np.inf
    npy = tmp / "x.npy"
    np.save(npy, lin)
    npy_raw = npy.read_bytes()
    npy.unlink()
    return {
        "good.png": bgr,
        "photo.jpg": bgr,
        "gray.png": cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY),
        "rgba_opaque.png": rgba,
        "rgba_holes.png": holes,
        "deep16.png": bgr.astype(np.uint16) * 257,
        "linear_float.npy": lin,
        "gray_float.npy": lin[..., 1].copy(),
        "black.png": np.zeros((H, W, 3), np.uint8),
        "white.png": np.full((H, W, 3), 255, np.uint8),
        "constant.png": np.full((H, W, 3), (40, 120, 200), np.uint8),
        "png_named.jpg": png,
        "tall_narrow.png": _photo(64, 320),
        "name with spaces é.png": bgr,
        "rgba_clear.png": clear,
        "empty.png": b"",
        "text.png": "hello, this is not an image\n",
        "text_named.jpg": "hello, this is not an image either\n",
        "gif_named.png": b"GIF89a\x01\x00\x01\x00\x00\x00\x00;",
        "truncated_png.png": png[: len(png) // 2],
        "flipped_png.png": _flip(png, _png_idat_offset(png)),
        "no_iend.png": png[:-12],
        "truncated_jpg.jpg": jpg[: len(jpg) // 2],
        "no_eoi.jpg": jpg[:-2],
        "bad_header.jpg": b"\x00" * 16 + jpg[16:],
        "truncated_tif.tif": tif[: len(tif) // 2],
        "garbage_tif.tif": b"II*\x00" + bytes(range(256)) * 2,
        "truncated_webp.webp": webp[: len(webp) // 2],
        "truncated_bmp.bmp": _encode(".bmp", bgr)[:700],
        "truncated_exr.exr": _exr_bytes(tmp / "x.exr")[:200],
        "one_pixel.png": np.zeros((1, 1, 3), np.uint8),
        "too_small.png": bgr[:59],
        "too_wide.png": _photo(4000, 60),
        "nan.npy": nan,
        "inf.npy": inf,
        "negative.npy": lin - 0.5,
        "flat_shape.npy": np.zeros(5, np.float32),
        "five_channels.npy": np.zeros((H, W, 5), np.float32),
        "int64.npy": np.zeros((H, W, 3), np.int64),
        "pickled.npy": np.array([{"a": 1}], dtype=object),
        "truncated_npy.npy": npy_raw[:300],
        "kept.png": bgr,  # its outputs exist already: refused without --overwrite
    }


#: name -> None (decomposed) or the problem its one-line error must state
BATCH_A = {
    "good.png": None,
    "photo.jpg": None,
    "gray.png": None,
    "rgba_opaque.png": None,
    "rgba_holes.png": None,
    "deep16.png": None,
    "linear_float.npy": None,
    "gray_float.npy": None,
    "black.png": None,
    "white.png": None,
    "constant.png": None,
    "png_named.jpg": None,
    "tall_narrow.png": None,
    "name with spaces é.png": None,
    "folder/UPPER.PNG": None,
    "rgba_clear.png": "alpha channel is fully transparent",
    "empty.png": "is empty (0 bytes)",
    "text.png": "is not an image OpenCV can decode",
    "text_named.jpg": "is not an image OpenCV can decode",
    "gif_named.png": "is not an image OpenCV can decode",
    "truncated_png.png": "is truncated or corrupt",
    "flipped_png.png": "CRC mismatch in the PNG IDAT chunk",
    "no_iend.png": "ends before the PNG IEND chunk",
    "truncated_jpg.jpg": "is truncated or corrupt",
    "no_eoi.jpg": "is truncated or corrupt",
    "bad_header.jpg": "is not an image OpenCV can decode",
    "truncated_tif.tif": "is truncated or corrupt",
    "garbage_tif.tif": "is truncated or corrupt",
    "truncated_webp.webp": "is truncated or corrupt",
    "truncated_bmp.bmp": "is not an image OpenCV can decode",
    "truncated_exr.exr": "OpenEXR",
    "one_pixel.png": "is 1x1 px; at least 60 px per side is needed",
    "too_small.png": "is 80x59 px; at least 60 px per side is needed",
    "too_wide.png": "smaller than the 60 px patches",
    "nan.npy": "contains 1 NaN or infinite values",
    "inf.npy": "contains 1 NaN or infinite values",
    "negative.npy": "has negative values",
    "flat_shape.npy": "has 1 dimensions; expected a 2-D image",
    "five_channels.npy": "has 5 channels",
    "int64.npy": "has pixel type int64",
    "pickled.npy": "is not a readable .npy array",
    "truncated_npy.npy": "is not a readable .npy array",
    "missing.png": "no such file",
    "dangling.png": "no such file",
    "kept.png": "exists; pass --overwrite to replace it",
}
if os.geteuid() != 0:  # root reads any file
    BATCH_A["unreadable.png"] = "cannot be read (permission denied)"


@pytest.fixture(scope="module")
def batch_a(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch_a")
    inputs = root / "in"
    inputs.mkdir()
    for name, payload in _batch_a_inputs(root).items():
        _write(inputs / name, payload)
    (inputs / "dangling.png").symlink_to(root / "nowhere" / "x.png")
    if "unreadable.png" in BATCH_A:
        _write(inputs / "unreadable.png", _photo())
        (inputs / "unreadable.png").chmod(0)
    folder = root / "folder"
    folder.mkdir()
    _write(folder / "UPPER.PNG", _photo())
    (folder / "notes.txt").write_text("not an image, and not taken from a folder")
    out = root / "out"
    out.mkdir()
    old = {n: f"old {n}".encode() for n in layer_file_names("kept")}
    for name, payload in old.items():
        (out / name).write_bytes(payload)
    args = [inputs / n for n in BATCH_A if "/" not in n and n != "missing.png"]
    args += [root / "missing.png", folder]
    run = run_cli(["decompose", *args, "-o", out, *FAST], cwd=root)  # stderr a pipe: no bar
    return run, root, out, old


def test_batch_a_exit_status_and_summary(batch_a):
    run, *_ = batch_a
    failed = sum(v is not None for v in BATCH_A.values())
    assert run.status == 1, run.stderr
    assert f"torchiid: {failed} of {len(BATCH_A)} input(s) failed" in run.lines
    _assert_clean(run)


@pytest.mark.parametrize("name", list(BATCH_A))
def test_batch_a_case(batch_a, name):
    run, _, out, _ = batch_a
    stem = Path(name).stem
    problem = BATCH_A[name]
    made = {p.name for p in out.iterdir() if p.name.startswith(f"{stem}-")}
    if problem is None:
        assert made == _set_names(stem)
        assert not run.errors_about(Path(name).name)
        info = json.loads((out / f"{stem}-info.json").read_text())
        assert info["input"].endswith(Path(name).name)
        refl = cv2.imread(str(out / f"{stem}-reflectance.png"), cv2.IMREAD_UNCHANGED)
        assert refl is not None and refl.dtype == np.uint8 and refl.ndim == 3
    else:
        errors = run.errors_about(Path(name).name)
        assert len(errors) == 1, run.stderr
        assert problem in errors[0], errors[0]
        if name != "kept.png":
            assert not made


def test_batch_a_keeps_existing_outputs_byte_identical(batch_a):
    _, _, out, old = batch_a
    assert {n: (out / n).read_bytes() for n in old} == old


def test_batch_a_leaves_no_temporary_files(batch_a):
    _, root, out, _ = batch_a
    assert _hidden(out) == []
    assert sorted(p.name for p in root.iterdir()) == ["folder", "in", "out"]


def test_batch_a_writes_lines_into_a_log_not_a_progress_bar(batch_a):
    run, *_ = batch_a
    assert "images:" not in run.stderr and "%|" not in run.stderr  # stderr is a pipe: no bar
    lines = run.stderr.splitlines()
    assert any(line.startswith("torchiid: error:") for line in lines)
    for line in lines:
        if "torchiid: error:" in line:
            assert line.startswith("torchiid: error:"), repr(line)
    done = [line for line in lines if " -> " in line]  # a line per image done, in its place
    assert done and all(" of " in line and "images/minute" in line for line in done)


def test_batch_a_transparent_pixels_are_outside_the_mask(batch_a):
    _, _, out, _ = batch_a
    refl = cv2.imread(str(out / "rgba_holes-reflectance.png"), cv2.IMREAD_UNCHANGED)
    assert (refl[:, : W // 2] == 0).all() and refl[:, W // 2 :].any()


def test_batch_a_refuses_each_bad_input_as_the_input_s_fault(batch_a):
    """Every bad file is an ``"input"`` failure (a rerun skips it), never an internal error."""
    _, _, out, _ = batch_a
    records = {}
    for line in (out / "manifest.jsonl").read_text().splitlines():
        record = json.loads(line)
        records[Path(record["input"]).name] = record
    assert set(records) == {Path(n).name for n in BATCH_A}
    for name, problem in BATCH_A.items():
        record = records[Path(name).name]
        if problem is None:
            assert record["status"] == "done" and record["failure"] is None, name
        else:
            kind = "output" if name == "kept.png" else "input"
            assert record["status"] == "failed" and record["failure"] == kind, name


# ------------------------------------------------------------------------------------------
# Batch B: --overwrite over an old set, an occupied output path, every optional file, umask

OPTIONAL = ["--save-npy", "--save-confidence", "--save-iterations"]


def _full_set(stem: str) -> set[str]:
    names = set(layer_file_names(stem, save_npy=True, save_confidence=True))
    names.add(f"{stem}-sigma.exr")
    return names | {f"{stem}-iter1-{x}.png" for x in ("sigma", "rho", "R", "S")}


@pytest.fixture(scope="module")
def batch_b(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch_b")
    for name in ("over.png", "occupied.png", "fresh.png"):
        _write(root / name, _photo())
    out = root / "out"
    out.mkdir()
    old = {n: b"old " + n.encode() for n in _full_set("over")}
    for name, payload in old.items():
        (out / name).write_bytes(payload)
    (out / "occupied-preview.png").mkdir()
    (out / "occupied-preview.png" / "keep.txt").write_text("a folder in the way")
    args = ["decompose", "over.png", "occupied.png", "fresh.png", "-o", out, "--overwrite"]
    run = run_cli([*args, *OPTIONAL, *FAST, "--no-progress"], cwd=root, umask=0o027)
    return run, out, old


def test_overwrite_replaces_a_complete_set_with_a_complete_set(batch_b):
    run, out, old = batch_b
    assert run.status == 1, run.stderr
    _assert_clean(run)
    made = {p.name for p in out.iterdir() if p.name.startswith("over-")}
    assert made == _full_set("over")
    assert all((out / n).read_bytes() != old[n] for n in old)
    assert Parameters.from_json(out / "over-params.json").iterations == 1


def test_an_occupied_output_path_fails_that_image_only(batch_b):
    run, out, _ = batch_b
    errors = run.errors_about("occupied")
    assert len(errors) == 1 and "occupied-preview.png: is a folder" in errors[0]
    assert (out / "occupied-preview.png" / "keep.txt").read_text() == "a folder in the way"
    assert {p.name for p in out.iterdir() if p.name.startswith("occupied-")} == {
        "occupied-preview.png"
    }
    assert {p.name for p in out.iterdir() if p.name.startswith("fresh-")} == _full_set("fresh")
    assert "torchiid: 1 of 3 input(s) failed" in run.lines
    assert _hidden(out) == []


def test_outputs_follow_the_umask(batch_b):
    _, out, _ = batch_b
    modes = {p.name: p.stat().st_mode & 0o777 for p in out.iterdir() if p.is_file()}
    assert set(modes.values()) == {0o640}, modes


# ------------------------------------------------------------------------------------------
# Usage and set-up errors: exit status 2 before any work (one forked process each)


def _setup_cases(root: Path) -> list[tuple[str, list, int, list[str], str | None]]:
    """(case, argv, status, what the one error line must contain, folder that must not exist)."""
    good = root / "good.png"
    _write(good, _photo())
    (root / "afile.txt").write_text("a file, not a folder")
    (root / "empty_dir").mkdir()
    (root / "dir.png").mkdir()
    _write(root / "twin.png", _photo())
    _write(root / "twin.jpg", _photo())
    params = {
        "malformed.json": b'{"iterations": 2,',
        "latin1.json": '{"feature_mode": "shared", "note": "café"}'.encode("latin-1"),
        "utf16.json": '{"iterations": 2}'.encode("utf-16"),
        "unknown_key.json": b'{"iterationz": 2}',
        "wrong_type.json": b'{"iterations": "three"}',
        "out_of_range.json": b'{"iterations": -1}',
        "nan.json": b'{"lambda_l": NaN}',
        "array.json": b"[1, 2]",
        "empty.json": b"",
    }
    for name, raw in params.items():
        (root / name).write_bytes(raw)
    (root / "params_dir.json").mkdir()
    _write(root / "mask_text.png", "not a mask")
    _write(root / "mask_empty.png", np.zeros((H, W), np.uint8))
    _write(root / "mask_small.png", np.full((30, 40), 255, np.uint8))
    o = root / "o"
    d = ["decompose", good, "-o", o, *FAST, "--no-progress"]
    cases = [
        ("output is a file", ["decompose", good, "-o", root / "afile.txt"], 2,
         ["afile.txt", "output exists and is not a directory"], None),
        ("output below a file", ["decompose", good, "-o", root / "afile.txt" / "sub"], 2,
         ["afile.txt/sub", "afile.txt is not a directory"], None),
        ("folder without images", ["decompose", root / "empty_dir", "-o", o], 2,
         ["empty_dir", "directory holds no image files"], "o"),
        ("folder named like an image", ["decompose", root / "dir.png", "-o", o], 2,
         ["dir.png", "directory holds no image files"], "o"),
        ("two inputs, one stem", ["decompose", root / "twin.png", root / "twin.jpg", "-o", o], 2,
         ["twin.png", "twin.jpg", "would write the same outputs"], "o"),
        ("--iterations 0", [*d[:4], "--iterations", "0"], 2, ["--iterations must be >= 1"], "o"),
        ("unknown preset", [*d, "--preset", "fastest"], 2, ["unknown preset 'fastest'"], "o"),
        ("unknown variant", [*d, "--variant", "v9"], 2, ["unknown variant 'v9'"], "o"),
        ("missing params file", [*d, "--params", root / "nope.json"], 2,
         ["nope.json", "no such parameter file"], "o"),
        ("params file is a folder", [*d, "--params", root / "params_dir.json"], 2,
         ["params_dir.json", "is a directory"], "o"),
        ("malformed params", [*d, "--params", root / "malformed.json"], 2,
         ["malformed.json", "not a readable JSON file"], "o"),
        ("non-UTF-8 params (Latin-1)", [*d, "--params", root / "latin1.json"], 2,
         ["latin1.json", "not a UTF-8 text file (byte 0xe9"], "o"),
        ("non-UTF-8 params (UTF-16)", [*d, "--params", root / "utf16.json"], 2,
         ["utf16.json", "not a UTF-8 text file"], "o"),
        ("params with an unknown key", [*d, "--params", root / "unknown_key.json"], 2,
         ["unknown_key.json", "Invalid parameter: iterationz"], "o"),
        ("params of the wrong type", [*d, "--params", root / "wrong_type.json"], 2,
         ["wrong_type.json", "iterations must be an integer"], "o"),
        ("params out of range", [*d, "--params", root / "out_of_range.json"], 2,
         ["out_of_range.json", "iterations must be > 0"], "o"),
        ("params with NaN", [*d, "--params", root / "nan.json"], 2,
         ["nan.json", "NaN is not a valid value"], "o"),
        ("params not an object", [*d, "--params", root / "array.json"], 2,
         ["array.json", "got a JSON array"], "o"),
        ("empty params file", [*d, "--params", root / "empty.json"], 2,
         ["empty.json", "not a readable JSON file"], "o"),
        ("missing mask", [*d, "--mask", root / "nomask.png"], 2,
         ["nomask.png", "no such file"], "o"),
        ("mask is not an image", [*d, "--mask", root / "mask_text.png"], 2,
         ["mask_text.png", "is not an image"], "o"),
        ("empty mask", [*d, "--mask", root / "mask_empty.png"], 2,
         ["mask_empty.png", "mask is empty"], "o"),
        ("mask of another size", [*d, "--mask", root / "mask_small.png"], 1,
         ["good.png", "is 80x64 px but the mask", "mask_small.png is 40x30 px"], "o"),
        ("every input fails", ["decompose", root / "nothing.png", "-o", o], 1,
         ["nothing.png", "no such file"], "o"),
        ("eval on a file", ["eval", "mit", good, "--no-progress", "-o", o], 2,
         ["good.png", "is a file, not a mit dataset directory"], "o"),
        ("eval on a missing folder", ["eval", "mit", root / "nodata", "-o", o], 2,
         ["nodata", "does not exist"], "o"),
        ("features of a bad file", ["features", root / "mask_text.png", "-o", o], 2,
         ["mask_text.png", "is not an image"], "o"),
        ("features below a file", ["features", good, "-o", root / "afile.txt" / "sub"], 2,
         ["afile.txt/sub", "afile.txt is not a directory"], None),
    ]  # fmt: skip
    if os.geteuid() != 0:
        locked = root / "locked"
        locked.mkdir()
        locked.chmod(0o555)
        cases += [
            ("unwritable output folder", ["decompose", good, "-o", locked], 2,
             ["locked", "cannot write into the output folder"], None),
            ("unwritable parent", ["decompose", good, "-o", locked / "sub"], 2,
             ["locked/sub", "cannot create the output folder"], None),
        ]  # fmt: skip
    else:  # root writes anywhere permissions allow nothing; sysfs refuses new entries
        unwritable = Path("/sys")
        if _refuses_entries(unwritable):
            cases += [
                ("unwritable output folder", ["decompose", good, "-o", unwritable], 2,
                 ["/sys", "cannot write into the output folder"], None),
                ("unwritable parent", ["decompose", good, "-o", unwritable / "torchiid-out"],
                 2, ["/sys/torchiid-out", "cannot create the output folder"], None),
            ]  # fmt: skip
    return cases


def _refuses_entries(folder: Path) -> bool:
    try:
        (folder / "torchiid-probe").mkdir()
    except OSError:
        return True
    (folder / "torchiid-probe").rmdir()
    return False


@pytest.fixture(scope="module")
def setup_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("setup")
    cases = _setup_cases(root)
    runs = run_many([c[1] for c in cases], cwd=root)
    return root, {c[0]: (c, r) for c, r in zip(cases, runs, strict=True)}


def _case_names() -> list[str]:
    with tempfile.TemporaryDirectory() as tmp:
        return [c[0] for c in _setup_cases(Path(tmp))]


@pytest.mark.parametrize("case", _case_names())
def test_usage_and_setup_errors(setup_runs, case):
    root, runs = setup_runs
    (name, argv, status, needles, absent), run = runs[case]
    assert run.status == status, run.stderr
    _assert_clean(run)
    errors = [line for line in run.lines if line.startswith("torchiid: error:")]
    assert len(errors) == 1, run.stderr
    for needle in needles:
        assert needle in errors[0], (needle, errors[0])
    if status == 2:
        assert len(run.stderr.strip().splitlines()) == 1, run.stderr
    if absent is not None:
        assert not (root / absent).exists()  # no output folder for a run that wrote nothing
    assert _hidden(root) == []


# ------------------------------------------------------------------------------------------
# Interrupts


def _old_set(out: Path, stem: str) -> dict[str, bytes]:
    out.mkdir(parents=True, exist_ok=True)
    old = {n: b"old " + n.encode() for n in layer_file_names(stem)}
    for name, payload in old.items():
        (out / name).write_bytes(payload)
    return old


def test_interrupt_while_writing_leaves_the_old_set(tmp_path):
    _write(tmp_path / "a.png", _photo())
    out = tmp_path / "out"
    old = _old_set(out, "a")
    args = ["decompose", "a.png", "-o", out, "--overwrite", *FAST, "--no-progress"]
    run = run_cli(args, cwd=tmp_path, env={"TORCHIID_TEST_INTERRUPT": "write:3"})
    assert run.status == 130, run.stderr
    _assert_clean(run)
    assert run.lines == [
        "torchiid: interrupted while processing a.png (nothing of it was written); "
        "0 of 1 input(s) written"
    ]
    assert _snapshot(out) == old
    assert _hidden(out) == []


def test_interrupt_while_renaming_completes_the_set_then_stops(tmp_path):
    _write(tmp_path / "a.png", _photo())
    _write(tmp_path / "b.png", _photo())
    out = tmp_path / "new" / "out"  # created with the first set
    args = ["decompose", "a.png", "b.png", "-o", out, *FAST, "--no-progress"]
    run = run_cli(args, cwd=tmp_path, env={"TORCHIID_TEST_INTERRUPT": "commit:4"})
    assert run.status == 130, run.stderr
    _assert_clean(run)
    assert run.lines == ["torchiid: interrupted; 1 of 2 input(s) written"]
    assert set(_snapshot(out)) == _set_names("a") | {"manifest.jsonl"}  # complete; b never started
    assert _hidden(tmp_path) == []


def test_interrupt_during_a_computation_leaves_nothing_of_that_image(tmp_path):
    _write(tmp_path / "a_quick.png", _photo())
    _write(tmp_path / "b_slow.png", _photo(480, 360))  # about 3 s at 5 iterations, 1 thread
    out = tmp_path / "out"
    args = ["decompose", "a_quick.png", "b_slow.png", "-o", out, "--iterations", "5"]
    terminal, stderr_end = pty.openpty()  # stderr a terminal: the progress bars are drawn
    size = struct.pack("HHHH", 24, 120, 0, 0)  # rows, columns: a bar needs a width
    fcntl.ioctl(stderr_end, termios.TIOCSWINSZ, size)
    proc = subprocess.Popen(
        [sys.executable, "-m", "torchiid.cli", *args],
        cwd=tmp_path,
        env=ENV,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=stderr_end,
    )
    os.close(stderr_end)
    seen, sent = b"", False
    while True:
        try:
            chunk = os.read(terminal, 4096)
        except OSError:  # EIO: the process has exited and closed the terminal
            break
        if not chunk:
            break
        seen += chunk
        if not sent and b"b_slow:" in seen:  # its iteration bar: the decomposition has begun
            proc.send_signal(signal.SIGINT)
            sent = True
    os.close(terminal)
    proc.wait(timeout=120)
    stderr = seen.decode(errors="replace")
    assert sent and proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert (
        "torchiid: interrupted while processing b_slow.png (nothing of it was written); "
        "1 of 2 input(s) written"
    ) in stderr
    assert set(_snapshot(out)) == _set_names("a_quick") | {"manifest.jsonl"}
    assert _hidden(out) == []
