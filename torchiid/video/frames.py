"""Where frames come from: a folder of images (sorted by name) or a video file (PyAV).

:func:`open_frames` returns a :class:`FrameSource`, an iterator of :class:`FrameItem`: frame by
frame, so a long video never sits in memory. A folder's frames are read with
:func:`torchiid.io.load_image` (every image format of ``decompose``; an alpha channel is a
mask); a frame that cannot be read is an item carrying its error, and the other frames go on.
Any other file is decoded with PyAV (``pip install 'torchiid[video]'``), 8-bit sRGB frames in
display order; the display-matrix rotation of phone videos is not applied.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchiid.core.colour import decode_lut
from torchiid.core.exceptions import ImageError, TorchiidError
from torchiid.io import IMAGE_SUFFIXES, load_image

__all__ = ["FrameItem", "FrameSource", "open_frames", "list_images", "MIN_FRAME_SIDE"]

#: the smallest frame side the method takes (its 60 px patches)
MIN_FRAME_SIDE = 60


@dataclass(frozen=True)
class FrameItem:
    """One frame of a :class:`FrameSource`.

    Attributes:
        index: 0-based position in the sequence.
        name: the frame's file name, or ``"<video> frame N"`` (1-based) for a video.
        image: ``(3, H, W)`` float32 linear RGB, or ``None`` when it could not be read.
        mask: ``(1, H, W)`` bool from an alpha channel, or ``None``.
        error: why the frame could not be read (a :class:`~torchiid.core.exceptions.
            TorchiidError` naming a folder's file; a video's frame is named by ``name``), or
            ``None``.
    """

    index: int
    name: str
    image: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    error: Exception | None = None


def list_images(folder: Path) -> list[Path]:
    """The image files of a folder (suffixes of :data:`torchiid.io.IMAGE_SUFFIXES`), sorted.

    Hidden files (macOS's ``._frame.png`` beside each frame) are left out.
    """
    try:
        found = sorted(
            q
            for q in folder.iterdir()
            if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES and not q.name.startswith(".")
        )
    except OSError as exc:
        raise TorchiidError(f"{folder}: cannot list ({exc.strerror or exc})") from None
    if not found:
        raise TorchiidError(
            f"{folder}: folder holds no image files ({', '.join(sorted(IMAGE_SUFFIXES))})"
        )
    return found


class FrameSource:
    """The frames of a folder or a video file, in order (see :func:`open_frames`).

    Attributes:
        path: the folder or file.
        kind: ``"folder"`` or ``"video"``.
        count: number of frames, or ``None`` when the video does not say.
        fps: frames per second of a video (``None`` for a folder).
        files: a folder's frame files (empty for a video).
    """

    def __init__(
        self,
        path: Path,
        kind: str,
        *,
        files: list[Path] | None = None,
        container: object | None = None,
        linear: bool = False,
    ) -> None:
        self.path = path
        self.kind = kind
        self.files = files or []
        self.linear = linear
        self._container = container
        self.count: int | None = len(self.files) if kind == "folder" else None
        self.fps: float | None = None
        if container is not None:
            stream = container.streams.video[0]
            self.count = int(stream.frames) or None
            rate = stream.average_rate or stream.guessed_rate
            self.fps = float(rate) if rate else None

    def __iter__(self) -> Iterator[FrameItem]:
        if self.kind == "folder":
            for i, f in enumerate(self.files):
                try:
                    loaded = load_image(f, linear=self.linear)
                except TorchiidError as exc:
                    yield FrameItem(i, f.name, error=exc)
                    continue
                yield FrameItem(i, f.name, loaded.image, loaded.mask)
            return
        yield from self._decode()

    def _decode(self) -> Iterator[FrameItem]:
        import av

        lut = decode_lut(8, self.linear)
        container = self._container
        i = 0
        try:
            for frame in container.decode(video=0):
                rgb = frame.to_ndarray(format="rgb24")
                name = f"{self.path.name} frame {i + 1}"
                h, w = rgb.shape[:2]
                if min(h, w) < MIN_FRAME_SIDE:
                    err = ImageError(
                        f"is {w}x{h} px; at least {MIN_FRAME_SIDE} px per side is needed"
                    )
                    yield FrameItem(i, name, error=err)
                else:
                    lin = np.take(lut, rgb)  # (H, W, 3) float32 linear
                    image = torch.from_numpy(np.ascontiguousarray(lin.transpose(2, 0, 1)))
                    yield FrameItem(i, name, image)
                i += 1
        except av.error.FFmpegError as exc:
            raise ImageError(
                f"{self.path}: cannot decode frame {i + 1} ({' '.join(str(exc).split())})"
            ) from None
        finally:
            self.close()

    def close(self) -> None:
        """Close the video file (nothing to do for a folder)."""
        if self._container is not None:
            self._container.close()
            self._container = None


def open_frames(path: str | os.PathLike, *, linear: bool = False) -> FrameSource:
    """Open a folder of frames or a video file.

    Args:
        path: a folder (its images, sorted by name, are the frames) or a video file (any
            container and codec FFmpeg decodes; needs PyAV).
        linear: a folder's 8/16-bit files hold linear values (as ``decompose --linear``).

    Returns:
        :class:`FrameSource`.

    Raises:
        TorchiidError: the path is missing, the folder holds no image, the file is a single
            image (use ``decompose``), PyAV is not installed, or the file is not a video.
    """
    path = Path(path)
    if path.is_dir():
        return FrameSource(path, "folder", files=list_images(path), linear=linear)
    if not path.exists():
        raise TorchiidError(f"{path}: no such file or folder")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        raise TorchiidError(
            f"{path}: is a single image; give a video file or a folder of frames "
            "(or use torchiid decompose)"
        )
    try:
        import av
    except ImportError:
        raise TorchiidError(
            f"{path}: reading video files needs PyAV: pip install 'torchiid[video]' (or pass "
            "a folder of frames)"
        ) from None
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, UnicodeDecodeError) as exc:
        raise TorchiidError(
            f"{path}: cannot open as a video ({' '.join(str(exc).split())})"
        ) from None
    if not container.streams.video:
        container.close()
        raise TorchiidError(f"{path}: holds no video stream")
    context = container.streams.video[0].codec_context
    w, h = int(context.width or 0), int(context.height or 0)
    if w and h and min(w, h) < MIN_FRAME_SIDE:  # every frame has the stream's size
        container.close()
        raise TorchiidError(
            f"{path}: its frames are {w}x{h} px; at least {MIN_FRAME_SIDE} px per side is needed"
        )
    return FrameSource(path, "video", container=container, linear=linear)
