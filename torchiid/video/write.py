"""Writing a decomposed video: one output set per frame, and an MP4 preview.

Frame ``i`` (0-based) of the sequence is written under the stem ``frame-XXXXXX`` with
``XXXXXX = i + 1`` (1-based, six digits, as ffmpeg numbers image sequences), with the files of
``torchiid decompose`` (:func:`torchiid.io.write_layers`) except ``-params.json``: the
parameters are written once, ``video-params.json``. Each frame's files are one
:class:`~torchiid.io.layers.OutputSet`: they appear together or not at all.

:class:`PreviewWriter` encodes ``[input | reflectance | shading / shading_white]`` (8-bit
sRGB, each panel at most 640 px on its longer side) as H.264 into a hidden temporary file in
the output folder and renames it into place (``preview.mp4``) when the sequence is complete.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Mapping
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchiid.core.exceptions import TorchiidError
from torchiid.io.layers import (
    ExtraOutputs,
    layer_file_names,
    panel_size,
    preview_row,
    srgb8_from_linear,
    write_layers,
)
from torchiid.io.output_set import OutputError, OutputSet, check_target
from torchiid.io.write import process_umask

__all__ = [
    "frame_stem",
    "frame_file_names",
    "write_frame",
    "PreviewWriter",
    "PREVIEW_NAME",
    "PARAMS_NAME",
    "PREVIEW_PANEL_SIDE",
]

#: the preview video's file name
PREVIEW_NAME = "preview.mp4"
#: the sequence's parameter file
PARAMS_NAME = "video-params.json"
#: longest side of each panel of the preview video
PREVIEW_PANEL_SIDE = 640


def frame_stem(index: int) -> str:
    """``frame-000001`` for the first frame (``index`` 0)."""
    return f"frame-{index + 1:06d}"


def frame_file_names(stem: str, *, save_npy: bool = False) -> list[str]:
    """Every file :func:`write_frame` writes for a frame."""
    names = layer_file_names(stem, save_npy=save_npy)
    return [n for n in names if not n.endswith("-params.json")]


def write_frame(
    output_set: OutputSet,
    stem: str,
    image: torch.Tensor,
    reflectance: torch.Tensor,
    shading: torch.Tensor,
    *,
    shading_white: float,
    info: Mapping[str, Any],
    mask: torch.Tensor | None = None,
    save_npy: bool = False,
) -> None:
    """Add one frame's files to ``output_set`` (the caller commits).

    Args:
        output_set: the frame's :class:`~torchiid.io.layers.OutputSet`.
        stem: :func:`frame_stem`.
        image: ``(3, H, W)`` linear frame.
        reflectance: ``(3, H, W)`` linear albedo.
        shading: ``(1, H, W)`` linear shading.
        shading_white: the sequence's ``shading_white``.
        info: entries of ``-info.json``.
        mask: ``(1, H, W)`` bool or ``None``.
        save_npy: also the float32 ``.npy`` pair.
    """
    write_layers(
        output_set.out,
        stem,
        image,
        reflectance,
        shading,
        shading_white=shading_white,
        info=info,
        mask=mask,
        extras=ExtraOutputs(npy=save_npy),
        output_set=output_set,
    )


class PreviewWriter:
    """``[input | reflectance | shading]`` frames into an H.264 MP4, put in place at the end.

    Args:
        path: the final file (e.g. ``OUT/preview.mp4``); its folder must exist when the first
            frame is added.
        fps: frames per second.
        overwrite: replace an existing file at :meth:`commit`.

    Raises:
        TorchiidError: PyAV is not installed (at the first frame).
        OutputError: the file cannot be written or exists without ``overwrite``.
    """

    def __init__(self, path: str | os.PathLike, fps: float = 24.0, *, overwrite: bool = False):
        self.path = Path(path)
        self.fps = fps
        self.overwrite = overwrite
        self.frames = 0
        self._tmp: Path | None = None
        self._container: Any = None
        self._stream: Any = None
        self._panel: tuple[int, int] | None = None

    def _open(self, h: int, w: int) -> None:
        try:
            import av
        except ImportError:
            raise TorchiidError(
                "the MP4 preview needs PyAV: pip install 'torchiid[video]'"
            ) from None
        ph, pw = self._panel = panel_size(h, w, PREVIEW_PANEL_SIDE, minimum=2)
        fd, tmp = tempfile.mkstemp(prefix=".torchiid-preview-", suffix=".mp4", dir=self.path.parent)
        os.close(fd)
        self._tmp = Path(tmp)
        try:
            self._container = av.open(str(self._tmp), mode="w", format="mp4")
            rate = Fraction(self.fps).limit_denominator(1001)
            stream = self._container.add_stream("libx264", rate=rate)
            width, height = 3 * pw + 8, ph
            stream.width, stream.height = width + width % 2, height + height % 2
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": "20"}
            self._stream = stream
        except (av.error.FFmpegError, OSError) as exc:
            self.discard()
            raise OutputError(f"{self.path}: cannot write ({' '.join(str(exc).split())})") from None

    def add(
        self, image: torch.Tensor, reflectance: torch.Tensor, shading_view: torch.Tensor
    ) -> None:
        """Append a frame: linear ``(3, H, W)`` image and reflectance, ``(1, H, W)`` shading view.

        The shading view is the shading divided by the sequence's ``shading_white``.
        """
        import av

        h, w = image.shape[-2:]
        if self._container is None:
            self._open(h, w)
        rgb = srgb8_from_linear(preview_row([image, reflectance, shading_view], self._panel))
        pad_h, pad_w = self._stream.height - rgb.shape[0], self._stream.width - rgb.shape[1]
        if pad_h or pad_w:
            rgb = np.pad(rgb, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        try:
            for packet in self._stream.encode(frame):
                self._container.mux(packet)
        except (av.error.FFmpegError, OSError) as exc:
            raise OutputError(f"{self.path}: cannot write ({' '.join(str(exc).split())})") from None
        self.frames += 1

    def commit(self) -> Path | None:
        """Finish the file and rename it into place; returns its path (``None``: no frame)."""
        import av

        if self._container is None:
            return None
        try:
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._container.close()
            self._container = None
            target = self.path
            check_target(target, self.overwrite)
            os.chmod(self._tmp, 0o666 & ~process_umask())
            os.replace(self._tmp, target)
            self._tmp = None
            return target
        except (av.error.FFmpegError, OSError) as exc:
            raise OutputError(f"{self.path}: cannot write ({' '.join(str(exc).split())})") from None
        finally:
            self.discard()

    def discard(self) -> None:
        """Drop the unfinished file."""
        if self._container is not None:
            with contextlib.suppress(Exception):
                self._container.close()
            self._container = None
        if self._tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(self._tmp)
            self._tmp = None
