"""The files the app writes: the layers as a zip, the edited photo, and where they live.

A server gets one temporary folder (:class:`ServerFolder`) that holds Gradio's cache
(uploads and the images it sends to the page) and a folder per photo for its downloads; it
is removed when the server stops. The layers are written by :func:`torchiid.io.write_layers`,
the function ``torchiid decompose`` writes its output folder with, so the zip holds the same
files as ``torchiid decompose --save-stage1`` (the last Stage 1 layers too, which
``torchiid edit --from`` needs for merge and the illumination edits).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import zipfile
from pathlib import Path

import torch

from torchiid.app.session import Session
from torchiid.io import layer_file_names, save_image, write_layers
from torchiid.io.output_set import OutputSet

__all__ = ["ServerFolder", "layer_names", "write_edited", "write_layers_zip"]

#: files whose bytes are compressed already are stored in the zip as they are
_STORED = (".png", ".exr")
#: the process's temporary folder, and Gradio's cache folder
_TMPDIR, _CACHE = "TMPDIR", "GRADIO_TEMP_DIR"


class ServerFolder:
    """A server's own temporary folder, removed with everything in it by :meth:`remove`.

    It holds Gradio's cache (``gradio/``), the photos' downloads (``sessions/``) and, once
    :meth:`activate` made it so, the process's temporary folder (``tmp/``: ``TMPDIR``), where
    the libraries put their own temporary files (ONNX Runtime leaves a small ``.ses`` file
    there, for one).

    Args:
        parent: where to create it (default: the system's temporary folder).
    """

    def __init__(self, parent: str | Path | None = None) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="torchiid-app-", dir=parent))
        self.gradio = self.root / "gradio"
        self.sessions = self.root / "sessions"
        self.tmp = self.root / "tmp"
        for folder in (self.gradio, self.sessions, self.tmp):
            folder.mkdir()
        self._saved: dict[str, str | None] | None = None

    def activate(self) -> None:
        """Make this the process's temporary folder and Gradio's cache, until :meth:`remove`.

        Gradio reads ``GRADIO_TEMP_DIR`` and the temporary folder when it is imported, so a
        server that is to leave nothing behind activates its folder before that.
        """
        if self._saved is None:
            self._saved = {k: os.environ.get(k) for k in (_TMPDIR, _CACHE)}
            self._saved_tempdir = tempfile.tempdir
        os.environ[_TMPDIR] = str(self.tmp)
        os.environ[_CACHE] = str(self.gradio)
        tempfile.tempdir = str(self.tmp)

    def session_folder(self) -> Path:
        """A new empty folder for one photo's downloads."""
        return Path(tempfile.mkdtemp(prefix="photo-", dir=self.sessions))

    def remove(self) -> None:
        """Remove the folder and everything in it; undo :meth:`activate`."""
        if self._saved is not None:
            for key, value in self._saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
            tempfile.tempdir = self._saved_tempdir
            self._saved = None
        shutil.rmtree(self.root, ignore_errors=True)


def layer_names(stem: str) -> list[str]:
    """The names of the files in the layers' zip (those of ``decompose --save-stage1``)."""
    return layer_file_names(stem) + [f"{stem}-sigma.exr", f"{stem}-rho.exr"]


def write_layers_zip(session: Session, folder: Path) -> Path:
    """Write the photo's layers as the CLI does and pack them into ``<stem>-layers.zip``.

    Args:
        session: the photo's session.
        folder: the session's download folder.

    Returns:
        the zip file's path.
    """
    stem = session.stem
    full = session.full
    out = Path(tempfile.mkdtemp(prefix="layers-", dir=folder))
    try:
        files = {
            f"{stem}-sigma.exr": "last Stage 1 shading sigma, float32 linear OpenEXR",
            f"{stem}-rho.exr": "last Stage 1 reflectance rho, float32 linear OpenEXR",
        }
        info = {**session.info, "written_by": "torchiid app", "files": files}
        with OutputSet(out, label=stem) as tx:
            write_layers(
                out,
                stem,
                full.image[0],
                full.reflectance[0],
                full.shading[0],
                shading_white=float(session.result.shading_white[0]),
                info=info,
                params_json=session.params.to_json(),
                mask=None if full.mask is None else full.mask[0],
                output_set=tx,
            )
            sigma, rho = full.sigma[0], full.rho[0]
            tx.write(f"{stem}-sigma.exr", lambda p: save_image(p, sigma, "exr"), background=True)
            tx.write(f"{stem}-rho.exr", lambda p: save_image(p, rho, "exr"), background=True)
            tx.commit()
        target = folder / f"{stem}-layers.zip"
        partial = folder / f".{stem}-layers.zip.part"
        with zipfile.ZipFile(partial, "w") as zf:
            for name in layer_names(stem):
                how = zipfile.ZIP_STORED if name.endswith(_STORED) else zipfile.ZIP_DEFLATED
                zf.write(out / name, name, compress_type=how)
        partial.replace(target)
        return target
    finally:
        shutil.rmtree(out, ignore_errors=True)


def write_edited(session: Session, image: torch.Tensor, folder: Path) -> Path:
    """Write the edited photo, ``(1, 3, H, W)`` linear, as ``<stem>-edited.png`` (8-bit sRGB)."""
    return save_image(folder / f"{session.stem}-edited.png", image[0], "srgb8")
