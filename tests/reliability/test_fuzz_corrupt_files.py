"""Seeded random corruptions of valid PNG and JPEG files, through the installed command.

50 corruptions (truncations, flipped bits, wrong headers) of one small PNG and one small JPEG
go through one ``torchiid decompose`` batch. For each, the command must either refuse the file
in one line naming it, leaving no output of it, or write a complete, valid decomposition. A
JPEG has no checksum, so altered bytes in its compressed data may still decode to a valid
(different) picture; a PNG's critical chunks carry CRCs, but bytes outside them (ancillary
chunks, trailing bytes) do not matter. So a decomposition is accepted only if it is built from
the pixels the file really holds, told apart from garbage by an independent decoder: Pillow,
in its strict mode (truncated images are errors), must decode the file completely and the
decomposition must reproduce Pillow's pixels, or, where Pillow refuses the file, reproduce the
original picture (the damage was outside the pixel data). "Reproduce" means that the exact
output pair, 16-bit linear reflectance times OpenEXR shading, gives back every 8-bit sRGB code
within 1. The gray filler OpenCV puts into a truncated JPEG, or any other decoded garbage,
fails that test.
"""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
from PIL import Image, ImageFile
from reliability_harness import run_cli
from skimage import data

from torchiid.core.colour import linear_to_srgb
from torchiid.io import layer_file_names, read_exr

SEED = 20240613
N = 50
MAGICS = [b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff\xe0", b"GIF89a", b"BM", b"II*\x00", b"RIFF"]


def _originals() -> dict[str, tuple[bytes, np.ndarray]]:
    rgb = cv2.resize(data.astronaut(), (80, 64), interpolation=cv2.INTER_AREA)
    out = {}
    for ext in ("png", "jpg"):
        ok, buf = cv2.imencode(f".{ext}", rgb[..., ::-1])
        assert ok
        raw = buf.tobytes()
        out[ext] = (raw, _strict_decode_bytes(raw))
    return out


def _strict_decode_bytes(raw: bytes) -> np.ndarray:
    import io

    with Image.open(io.BytesIO(raw)) as im:
        im.load()
        return np.asarray(im.convert("RGB"))


def _strict_decode(path) -> np.ndarray | None:
    """Pillow's pixels of a file it decodes completely, else ``None``."""
    assert not ImageFile.LOAD_TRUNCATED_IMAGES
    try:
        with Image.open(path) as im:
            im.load()
            return np.asarray(im.convert("RGB"))
    except Exception:  # noqa: BLE001 - any refusal (warnings are errors under pytest, too)
        return None


def _corrupt(rng: np.random.Generator, raw: bytes, kind: str) -> bytes:
    if kind == "truncate":
        return raw[: int(rng.integers(1, len(raw)))]
    if kind == "flip":
        b = bytearray(raw)
        for _ in range(int(rng.integers(1, 5))):
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
        return bytes(b)
    # a wrong header: random bytes, or another format's signature, over the first bytes
    if rng.random() < 0.5:
        head = MAGICS[int(rng.integers(0, len(MAGICS)))]
    else:
        head = rng.integers(0, 256, int(rng.integers(1, 17)), dtype=np.uint8).tobytes()
    return head + raw[len(head) :]


def _cases():
    rng = np.random.default_rng(SEED)
    originals = _originals()
    cases = []
    for i in range(N):
        ext = ("png", "jpg")[i % 2]
        kind = ("truncate", "flip", "header")[(i // 2) % 3]
        raw, pixels = originals[ext]
        cases.append((f"fuzz{i:02d}_{kind}.{ext}", _corrupt(rng, raw, kind), pixels))
    return cases


def _reconstructed_codes(out, stem) -> np.ndarray:
    r16 = cv2.imread(str(out / f"{stem}-reflectance-linear16.png"), cv2.IMREAD_UNCHANGED)
    s, _ = read_exr(out / f"{stem}-shading.exr")
    lin = r16[..., ::-1].astype(np.float64) / 65535 * s[..., None]
    srgb = linear_to_srgb(__import__("torch").from_numpy(lin.astype(np.float32))).numpy()
    return np.round(np.clip(srgb, 0, 1) * 255).astype(np.int16)


@pytest.fixture(scope="module")
def fuzz_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    files = root / "in"
    files.mkdir()
    cases = _cases()
    for name, raw, _ in cases:
        (files / name).write_bytes(raw)
    out = root / "out"
    run = run_cli(["decompose", files, "-o", out, "--iterations", "1", "--no-progress"], root)
    return run, files, out, cases


def test_no_traceback_and_an_honest_exit_status(fuzz_run):
    run, _, _, cases = fuzz_run
    assert "Traceback" not in run.stderr and "[ERROR" not in run.stderr, run.stderr
    assert "[ WARN" not in run.stderr, run.stderr
    # nothing but torchiid's own lines: what libjpeg/libpng/OpenCV print is collected and logged
    assert all(line.startswith("torchiid: ") for line in run.stderr.splitlines()), run.stderr
    failed = len([line for line in run.lines if line.startswith("torchiid: error:")])
    assert 0 < failed < len(cases)  # the seed gives both outcomes
    assert run.status == 1
    assert f"torchiid: {failed} of {len(cases)} input(s) failed" in run.lines


def test_every_corruption_is_refused_cleanly_or_decomposed_from_real_pixels(fuzz_run):
    run, files, out, cases = fuzz_run
    outcomes = {"refused": 0, "decoded": 0}
    for name, _, original in cases:
        stem = name.rsplit(".", 1)[0]
        made = {p.name for p in out.iterdir() if p.name.startswith(f"{stem}-")}
        errors = run.errors_about(name)
        if errors:
            assert len(errors) == 1 and not made, (name, errors, made)
            assert re.search(r"torchiid: error: \S*" + re.escape(name) + r": \w", errors[0])
            outcomes["refused"] += 1
            continue
        assert made == set(layer_file_names(stem)) | {f"{stem}-sigma.exr"}, name
        codes = _reconstructed_codes(out, stem)
        reference = _strict_decode(files / name)
        if reference is None or reference.shape != codes.shape:
            reference = original  # Pillow refused it: the damage must be outside the pixels
        assert reference.shape == codes.shape, name
        worst = int(np.abs(codes - reference.astype(np.int16)).max())
        assert worst <= 1, f"{name}: decomposed pixels differ from the file's by {worst} codes"
        outcomes["decoded"] += 1
    assert outcomes["refused"] >= 25 and outcomes["decoded"] >= 1, outcomes
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]
