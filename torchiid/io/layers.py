"""Writing a decomposition to files: what ``torchiid decompose`` leaves in its output folder.

For an input ``photo.jpg`` (``stem = "photo"``):

========================================  ====================================================
file                                      what it is
========================================  ====================================================
``photo-reflectance.png``                 reflectance ``R``, 8-bit **sRGB**; ``R`` is an albedo
                                          in [0, 1], so nothing is clipped
``photo-shading.png``                     shading ``S / shading_white``, 8-bit **sRGB** gray;
                                          ``shading_white`` (the shading's 99th percentile,
                                          recorded in ``photo-info.json``) shows as white,
                                          the brightest 1% clip
``photo-preview.png``                     ``[I | R | S / shading_white]`` side by side, sRGB,
                                          each panel at most 1024 px on its longer side
``photo-reflectance-linear16.png``        ``R``, 16-bit **linear** PNG, unclipped
``photo-shading.exr``                     ``S``, 32-bit float **linear** OpenEXR (one channel
                                          ``Y``), unclipped, values may exceed 1
``photo-info.json``                       sizes, ``shading_white``, ``albedo_excess``, the
                                          scale convention, what each file is and the
                                          ``torchiid_version`` that wrote them
``photo-params.json``                     every parameter used (the format ``--params`` reads)
``photo-reflectance.npy`` / ``-shading``  with ``save_npy``: float32 linear ``(H, W, 3)`` and
                                          ``(H, W)``, ``R · S == I`` to float precision
``photo-confidence.png``                  with ``save_confidence``: 8-bit gray, 255 where the
                                          pixel's colour is trusted, 0 where it is dark or
                                          clipped (no information, shading continued smoothly)
``photo-sigma.exr``                       Stage 1's last shading ``σ``, float32 linear OpenEXR
                                          (``decompose`` adds it to the set; ``ρ = I / σ``)
========================================  ====================================================

OpenEXR rather than a float TIFF for the shading: it is the interchange format for linear HDR
images (OpenCV, imageio, Pillow plug-ins, GIMP, Photoshop, Krita, Blender, Nuke, darktable and
the macOS viewer open it), it is lossless-compressed (ZIP) and its header holds metadata, here
``shading_white`` and the convention. Float TIFFs are opened by fewer viewers and often shown
clipped.

The exact pair: the EXR shading is written as the per-pixel least-squares fit
``S = Σ_c I_c R_c / Σ_c R_c²`` to the **quantised** 16-bit reflectance ``R_c``, so that
``R_png16 · S_exr`` reproduces the linear image as closely as 16-bit ``R`` allows (relative
error at most ``1 / (2 · 65535 · R_c)``); the ``.npy`` pair is the float32 result itself.

Every full-resolution conversion runs in bands of rows, so writing a 24-megapixel result needs
only its 8- and 16-bit arrays besides the layers.

One image's files are one **output set** (:class:`OutputSet`): they are written under their own
names into a hidden temporary folder ``.torchiid-<stem>-<random>`` inside the output folder and
renamed into place together only when every one of them is complete. An error, a
``KeyboardInterrupt`` (Ctrl-C) or SIGTERM before that removes the temporary folder, so the
output folder holds either nothing new or the complete set; SIGINT and SIGTERM arriving during
the renames are held until the set is in place. With ``overwrite`` the files of an old set are
replaced only then, and put back if a rename fails. The output folder (and missing parents) is
created when the first file of a set is written, and removed again when that set is discarded
and the folder is still empty. Only SIGKILL or a power loss can leave the hidden folder behind
(and, during the renames, a mix of old and new files, the old ones in that folder).

``TORCHIID_TEST_INTERRUPT`` (tests only) raises SIGINT in the process at a fixed point:
``write:N`` when the set's ``N + 1``-th file is about to be written, ``commit:N`` after the
``N``-th rename into place.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from torchiid._version import __version__
from torchiid.core.colour import srgb8_encode_lut
from torchiid.core.exceptions import TorchiidError
from torchiid.io.image import encode_codes, save_encoded, save_image
from torchiid.resample import row_bands

__all__ = [
    "check_output_folder",
    "LayerFiles",
    "OutputSet",
    "OutputError",
    "layer_file_names",
    "make_folders",
    "remove_empty_folders",
    "write_layers",
    "srgb8_from_linear",
]

#: longest side of each panel of the preview
PREVIEW_SIDE = 1024

#: what each file is, for ``-info.json`` and the README
DESCRIPTIONS = {
    "reflectance.png": "reflectance R (albedo in [0, 1]), 8-bit sRGB",
    "shading.png": "shading S / shading_white, 8-bit sRGB (values above shading_white clip)",
    "preview.png": "[image | reflectance | shading / shading_white], 8-bit sRGB, downscaled",
    "reflectance-linear16.png": "reflectance R, 16-bit linear, unclipped",
    "shading.exr": "shading S, 32-bit float linear OpenEXR (channel Y), unclipped",
    "info.json": "sizes, scale convention and the factors to recover other conventions",
    "params.json": "every parameter used (readable with --params)",
    "reflectance.npy": "reflectance R, float32 linear (H, W, 3)",
    "shading.npy": "shading S, float32 linear (H, W)",
    "confidence.png": "pixel confidence, 8-bit gray: 255 trusted, 0 dark or clipped",
}

LayerFiles = dict[str, Path]


def _linear16(x: torch.Tensor) -> np.ndarray:
    """``(C, h, w)`` linear values, clipped to [0, 1], as ``(h, w, C)`` uint16 codes."""
    q = x.detach().to("cpu", torch.float32).clamp(0, 1).mul_(65535).round_()
    return q.to(torch.int32).permute(1, 2, 0).numpy().astype(np.uint16)


def srgb8_from_linear(x: torch.Tensor) -> np.ndarray:
    """``(C, H, W)`` linear values (clipped to [0, 1]) as an ``(H, W, C)`` uint8 sRGB array."""
    return srgb8_encode_lut()[_linear16(x)]


def layer_file_names(
    stem: str, *, save_npy: bool = False, save_confidence: bool = False
) -> list[str]:
    """Every file name :func:`write_layers` writes for ``stem``, in writing order."""
    keys = [
        "reflectance-linear16.png",
        "shading.exr",
        "reflectance.png",
        "shading.png",
        "preview.png",
    ]
    if save_npy:
        keys += ["reflectance.npy", "shading.npy"]
    if save_confidence:
        keys += ["confidence.png"]
    keys += ["info.json", "params.json"]
    return [f"{stem}-{k}" for k in keys]


def _preview_panel(x: torch.Tensor) -> torch.Tensor:
    h, w = x.shape[-2:]
    s = PREVIEW_SIDE / max(h, w)
    if s >= 1:
        return x
    size = (max(1, round(h * s)), max(1, round(w * s)))
    return F.interpolate(x[None], size=size, mode="area")[0]


class OutputError(TorchiidError):
    """An output file or folder cannot be written (the message names it and says why)."""


def _why(exc: OSError) -> str:
    return exc.strerror or " ".join(str(exc).split()) or type(exc).__name__


def make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; returns the folders it created, innermost first.

    Raises:
        OutputError: the folder cannot be created (the message names it and says why).
    """
    missing = []
    here = folder
    while not here.exists() and here != here.parent:
        missing.append(here)
        here = here.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot create the output folder ({_why(exc)})") from None
    finally:
        created = [d for d in missing if d.is_dir()]
    return created


def remove_empty_folders(created: list[Path]) -> None:
    """Remove folders made by :func:`make_folders` (innermost first) while they are empty."""
    for folder in created:
        try:
            folder.rmdir()
        except OSError:
            break


_HELD = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM during the block and deliver them after it (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous: dict[int, Any] = {}
    for sig in _HELD:
        handler = signal.getsignal(sig)
        if handler is None or handler is signal.SIG_IGN:
            continue  # installed outside Python, or ignored: leave it alone
        previous[sig] = signal.signal(sig, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if received:
            signal.raise_signal(received[0])


def _test_interrupt(stage: str, count: int) -> None:
    """The ``TORCHIID_TEST_INTERRUPT`` hook of the tests (see the module notes)."""
    want = os.environ.get("TORCHIID_TEST_INTERRUPT")
    if want and want == f"{stage}:{count}":
        signal.raise_signal(signal.SIGINT)


class OutputSet:
    """The files of one image, written under temporary names and put in place together.

    Write each file with :meth:`write`, then call :meth:`commit`; used as a context manager,
    the set is discarded (temporary files removed, nothing else touched) when the block ends
    with an exception, ``KeyboardInterrupt`` included, and is otherwise left to the caller to
    commit. See the module notes for the guarantees.

    Args:
        out_dir: the output folder; created, with missing parents, by the first :meth:`write`.
        overwrite: replace existing files of the same names at :meth:`commit` (else an existing
            file makes the commit fail and the old file stays as it was).
        label: part of the temporary folder's name (e.g. the image's stem).

    Raises:
        OutputError: (from :meth:`write` and :meth:`commit`) a file or folder cannot be
            written; the message names the output file, never a temporary name.
    """

    def __init__(
        self, out_dir: str | os.PathLike, *, overwrite: bool = True, label: str = "set"
    ) -> None:
        self.out = Path(out_dir)
        self.overwrite = overwrite
        self.label = label
        self.names: list[str] = []
        self.committed = False
        self._tmp: Path | None = None
        self._created: list[Path] = []

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if kind is not None:
            self.discard()

    def _start(self) -> Path:
        self._created = make_folders(self.out)
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".torchiid-{self.label}-", dir=self.out))
            (self._tmp / "new").mkdir()
        except OSError as exc:
            self.discard()
            raise OutputError(
                f"{self.out}: cannot write into the output folder ({_why(exc)})"
            ) from None
        return self._tmp

    def write(self, name: str, write: Callable[[Path], Any]) -> Path:
        """Let ``write(path)`` write the file ``name`` of the set; returns its final path."""
        if "/" in name or os.sep in name or name in ("", ".", ".."):
            raise ValueError(f"an output file name must be a plain name, got {name!r}")
        if name in self.names:
            raise ValueError(f"{name} is already part of this output set")
        _test_interrupt("write", len(self.names))
        tmp = self._tmp if self._tmp is not None else self._start()
        self.names.append(name)
        try:
            write(tmp / "new" / name)
        except OSError as exc:
            raise OutputError(f"{self.out / name}: cannot write ({_why(exc)})") from None
        return self.out / name

    def commit(self) -> list[Path]:
        """Rename every file of the set into place; returns their paths.

        Raises:
            OutputError: a target is a folder, a target exists without ``overwrite``, or a
                rename failed; the old files are back in place and the new ones removed.
        """
        if self._tmp is None:
            return []
        new, old = self._tmp / "new", self._tmp / "old"
        targets = [self.out / n for n in self.names]
        with _signals_held():
            try:
                for target in targets:
                    if target.is_dir() and not target.is_symlink():
                        raise OutputError(f"{target}: is a folder; cannot replace it by an output")
                    if not self.overwrite and os.path.lexists(target):
                        raise OutputError(f"{target} exists; pass --overwrite to replace it")
                moved: list[tuple[Path, Path]] = []
                placed: list[Path] = []
                try:
                    old.mkdir()
                    for name, target in zip(self.names, targets, strict=True):
                        if os.path.lexists(target):
                            os.replace(target, old / name)
                            moved.append((old / name, target))
                        os.replace(new / name, target)
                        placed.append(target)
                        _test_interrupt("commit", len(placed))
                except OSError as exc:
                    for path in reversed(placed):
                        with contextlib.suppress(OSError):
                            os.unlink(path)
                    for backup, target in reversed(moved):
                        with contextlib.suppress(OSError):
                            os.replace(backup, target)
                    where = targets[len(placed)] if len(placed) < len(targets) else self.out
                    raise OutputError(f"{where}: cannot write ({_why(exc)})") from None
                self.committed = True
            finally:
                self._remove_tmp()
            self._created = []  # they hold the set now
        return targets

    def discard(self) -> None:
        """Remove the temporary files, and the folders the set created if they are empty."""
        with _signals_held():
            self._remove_tmp()
            remove_empty_folders(self._created)
            self._created = []

    def _remove_tmp(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None


def check_output_folder(out_dir: str | os.PathLike) -> None:
    """Check, before any work, that output files can be written into ``out_dir``.

    An existing folder is probed by creating (and removing) a hidden file in it; a missing one
    is not created (:class:`OutputSet` creates it with the first file), but its nearest
    existing parent must be a folder in which a folder can be created (probed likewise).

    Raises:
        OutputError: ``out_dir`` or one of its parents is a file, or nothing can be created
            there; the message names the folder and the reason.
    """
    out = Path(out_dir)
    if out.exists():
        if not out.is_dir():
            raise OutputError(f"{out}: output exists and is not a directory")
        try:
            fd, probe = tempfile.mkstemp(prefix=".torchiid-probe-", dir=out)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise OutputError(f"{out}: cannot write into the output folder ({_why(exc)})") from None
        return
    parent = out
    while not parent.exists():
        if parent.is_symlink():
            raise OutputError(f"{out}: cannot create the output folder: {parent} is a broken link")
        if parent == parent.parent:
            break
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{out}: cannot create the output folder: {parent} is not a directory")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".torchiid-probe-", dir=parent))
    except OSError as exc:
        raise OutputError(
            f"{out}: cannot create the output folder in {parent} ({_why(exc)})"
        ) from None


def _write_text(text: str) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        path.write_text(text, encoding="utf-8")

    return write


def write_layers(
    out_dir: str | os.PathLike,
    stem: str,
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    *,
    shading_white: float,
    info: Mapping[str, Any] | None = None,
    params_json: str | None = None,
    mask: torch.Tensor | None = None,
    confidence: torch.Tensor | None = None,
    save_npy: bool = False,
    overwrite: bool = True,
    output_set: OutputSet | None = None,
) -> LayerFiles:
    """Write one image's layers as one output set (see the module notes for the files).

    Args:
        out_dir: the output folder (created if missing).
        stem: file name stem.
        image: ``(3, H, W)`` linear input (the preview's first panel and the EXR fit).
        reflectance: ``(3, H, W)`` linear albedo in [0, 1].
        shading: ``(1, H, W)`` linear gray shading.
        shading_white: the shading value shown as white in the viewable PNG.
        info: extra entries for ``-info.json``; its ``"files"`` (name -> description) are added
            to the list of files, for files the caller writes into the same set.
        params_json: text of ``-params.json`` (omitted when ``None``).
        mask: ``(1, H, W)`` bool; outside it the EXR shading is 0 like the layers.
        confidence: ``(1, H, W)`` in [0, 1]: written as ``-confidence.png`` when given.
        save_npy: also write the float32 ``.npy`` pair.
        overwrite: replace existing files (else :class:`OutputError` if one exists, before
            anything is computed or written).
        output_set: add the files to this :class:`OutputSet` (of ``out_dir``) and leave it to
            the caller to add more and commit; by default the files are committed here.

    Returns:
        ``{suffix: path}`` of every file (in place, or to be put in place by the caller's
        commit).

    Raises:
        OutputError: a file cannot be written or exists without ``overwrite``; no file of
            the set was put in place (old files are unchanged).
    """
    if output_set is None:
        with OutputSet(out_dir, overwrite=overwrite, label=stem) as tx:
            existing = [tx.out / f"{stem}-{k}" for k in _keys(save_npy, confidence, params_json)]
            existing = [p for p in existing if os.path.lexists(p)]
            if existing and not overwrite:
                raise OutputError(f"{existing[0]} exists; pass --overwrite to replace it")
            files = write_layers(
                out_dir,
                stem,
                image,
                reflectance,
                shading,
                shading_white=shading_white,
                info=info,
                params_json=params_json,
                mask=mask,
                confidence=confidence,
                save_npy=save_npy,
                output_set=tx,
            )
            tx.commit()
        return files
    _, big_h, big_w = reflectance.shape
    r16 = np.empty((big_h, big_w, 3), np.uint16)
    s_exr = np.empty((big_h, big_w), np.float32)
    s8 = np.empty((big_h, big_w), np.uint8)
    white = float(shading_white) if shading_white > 0 else 1.0
    for rows in row_bands(big_h, big_w):
        q = _linear16(reflectance[:, rows])
        r16[rows] = q
        rq = torch.from_numpy(q.astype(np.float32)).permute(2, 0, 1).div_(65535)
        i_band = image[:, rows].detach().to("cpu", torch.float32)
        num, den = (i_band * rq).sum(0), (rq * rq).sum(0)
        exact = shading[0, rows].detach().to("cpu", torch.float32)
        fit = torch.where(den > 0, num / den.clamp_min(1e-30), exact)
        if mask is not None:
            fit = fit * mask[0, rows].to("cpu", torch.float32)
        s_exr[rows] = fit.numpy()
        s8[rows] = srgb8_from_linear(exact[None] / white)[..., 0]
    files: LayerFiles = {}

    def put(key: str, write: Callable[[Path], Any]) -> None:
        files[key] = output_set.write(f"{stem}-{key}", write)

    exr_header = {"shading_white": white, "convention": "torchiid albedo [0,1]"}
    r8 = srgb8_encode_lut()[r16]
    panels = [
        _preview_panel(x.detach().to("cpu", torch.float32)).expand(3, -1, -1)
        for x in (image, reflectance, shading / white)
    ]
    sep = torch.ones(3, panels[0].shape[1], 4)
    prev = torch.cat([panels[0], sep, panels[1], sep, panels[2]], dim=2)
    pngs = {
        "reflectance-linear16.png": r16,
        "reflectance.png": r8,
        "shading.png": s8,
        "preview.png": srgb8_from_linear(prev),
    }
    if confidence is not None:
        conf = (confidence.detach().to("cpu", torch.float32)[0] * 255).round_().to(torch.uint8)
        pngs["confidence.png"] = conf.numpy()
    # the PNGs are encoded in two threads (OpenCV releases the GIL; the 16-bit reflectance of a
    # 12 MP photo takes about a second, the others together half that), and the files are
    # written in their usual order as their encodings arrive. Leaving the block waits for the
    # encoders, also on an interrupt.
    with ThreadPoolExecutor(2, thread_name_prefix="torchiid-png") as pool:
        encoded = {key: pool.submit(encode_codes, arr) for key, arr in pngs.items()}
        del pngs, r16, r8

        def png(key: str) -> None:
            put(key, lambda p: save_encoded(p, encoded.pop(key).result()))

        png("reflectance-linear16.png")
        put("shading.exr", lambda p: save_image(p, s_exr, "exr", metadata=exr_header))
        for key in ("reflectance.png", "shading.png", "preview.png"):
            png(key)
        if save_npy:
            put("reflectance.npy", lambda p: save_image(p, reflectance, "npy"))
            put("shading.npy", lambda p: save_image(p, shading, "npy"))
        if "confidence.png" in encoded:
            png("confidence.png")
    record = {
        "torchiid_version": __version__,  # so a reader can interpret or migrate the files
        "size": [big_w, big_h],
        "shading_white": white,
        "convention": (
            "linear R*S = I; R is an albedo in [0, 1] whose albedo_quantile quantile of the "
            "brightest channel is 1 (pixels above moved their excess into S); S may exceed 1. "
            "(R*shading_white, S/shading_white) is the convention where the shading's 99th "
            "percentile is 1."
        ),
        **{k: v for k, v in (info or {}).items() if k != "files"},
        "files": {
            **{
                f"{stem}-{k}": DESCRIPTIONS[k]
                for k in [*files, "info.json"]
                + (["params.json"] if params_json is not None else [])
            },
            **dict((info or {}).get("files", {})),  # files the caller adds to the set
        },
    }
    put("info.json", _write_text(json.dumps(record, indent=2, allow_nan=False) + "\n"))
    if params_json is not None:
        put("params.json", _write_text(params_json))
    return files


def _keys(save_npy: bool, confidence: torch.Tensor | None, params_json: str | None) -> list[str]:
    names = layer_file_names("", save_npy=save_npy, save_confidence=confidence is not None)
    keys = [n[1:] for n in names]
    return keys if params_json is not None else [k for k in keys if k != "params.json"]
