"""What is the same for every image of a run: :class:`RunSettings` and its hash.

:func:`params_hash` names what makes an image's files; the manifest (:mod:`.manifest`) and
each image's ``-info.json`` record it, so a rerun knows which files are this decomposition.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

from torchiid.params import Parameters

__all__ = ["RETINEX_DEFAULTS", "RunSettings", "file_sha256", "params_hash"]

RETINEX_DEFAULTS = {"threshold_gray": 0.075, "threshold_color": 1.0}

#: bytes read at a time when hashing an input
HASH_CHUNK = 1 << 20


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 hex digest of a file, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


@dataclass(frozen=True)
class RunSettings:
    """Everything about a run that is the same for every image (picklable, sent to workers).

    Attributes:
        out: the output folder (an absolute path when workers on other machines use it).
        params: the method's parameters.
        method: ``"semantic"`` or ``"retinex"``.
        linear: 8/16-bit files hold linear values.
        device: ``"cpu"``, ``"cuda"`` or ``"auto"`` (resolved in each worker).
        overwrite: replace existing output files.
        save_npy, save_confidence, save_stage1, save_iterations: the optional files
            (``save_stage1``: Stage 1's ``-rho.exr``; its ``-sigma.exr`` is always written by
            the semantic method, for ``torchiid edit --from``).
        mask: a mask file for every image, or ``None``.
        mask_sha256: its SHA-256 (part of :attr:`params_hash`).
        threads: torch threads in each worker process (``None``: leave them as they are).
        redo: compute every image again, even where its complete files are there already.
    """

    out: Path
    params: Parameters
    method: str = "semantic"
    linear: bool = False
    device: str = "auto"
    overwrite: bool = False
    save_npy: bool = False
    save_confidence: bool = False
    save_stage1: bool = False
    save_iterations: bool = False
    mask: Path | None = None
    mask_sha256: str | None = None
    threads: int | None = None
    redo: bool = False

    @property
    def params_hash(self) -> str:
        """:func:`params_hash` of these settings."""
        return params_hash(self)


def params_hash(settings: RunSettings) -> str:
    """SHA-256 of what makes an image's files: the parameters and the options that change them.

    The canonical JSON (sorted keys, no spaces) of the full parameter set, the method, whether
    8/16-bit files are linear, the optional files asked for and the SHA-256 of the ``--mask``
    file. Not in it: the torchiid version (a rerun after an upgrade skips what is done;
    ``redo`` makes it again); the device, ``overwrite``, ``redo``, threads and workers, which
    change where and how fast the files are made, not which (the solvers' float sums may
    differ in the last digits between devices and thread counts).
    """
    what = {
        # the parameters alone, not the version that wrote them: a new version that computes
        # the same files keeps the collection's hashes
        "params": settings.params.to_dict(),
        "method": settings.method,
        "linear": settings.linear,
        "save_npy": settings.save_npy,
        "save_confidence": settings.save_confidence,
        "save_stage1": settings.save_stage1 and settings.method == "semantic",
        "save_iterations": settings.save_iterations and settings.method == "semantic",
        "mask_sha256": settings.mask_sha256,
    }
    text = json.dumps(what, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()
