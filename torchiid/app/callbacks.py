"""The page's callbacks: plain functions from the controls' values to the outputs' values.

Each takes what Gradio passes (file paths, numbers, the tab's :class:`Session` from a
``gr.State``) and returns what the output components show (uint8 images, Markdown, file
paths), so the tests call them directly. Every error a user can cause (a file that is not a
photo, a photo over the memory limit, a bad value) reaches the page as a ``gr.Error`` with
the library's one-line message; an unexpected one as a one-line "internal error" (its
traceback goes to the server's log), never as a traceback in the page.
"""

from __future__ import annotations

import functools
import logging
import shutil
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np

from torchiid.app.config import AppConfig
from torchiid.app.edits import EditSettings, load_texture, render, texture_of
from torchiid.app.files import ServerFolder, write_edited, write_layers_zip
from torchiid.app.objects import highlight
from torchiid.app.session import Session, open_photo, srgb8, view_shading
from torchiid.core.exceptions import TorchiidError, one_line, unimportable_dependency
from torchiid.params import Parameters

__all__ = [
    "CLEARED",
    "COMPARE",
    "EDIT_FIELDS",
    "Callbacks",
    "Selection",
    "forget",
    "settings_from",
]

log = logging.getLogger("torchiid")

#: the edit controls, in the order the page passes their values
EDIT_FIELDS = tuple(f.name for f in fields(EditSettings))
#: what the before/after slider compares the photo with
COMPARE = ("edited photo", "edited reflectance", "edited shading")


@dataclass(frozen=True)
class Selection:
    """The selected object: the proposals under the click and which of them is chosen."""

    candidates: tuple[int, ...]
    index: int = 0

    @property
    def proposal(self) -> int:
        """The chosen proposal."""
        return self.candidates[min(max(self.index, 0), len(self.candidates) - 1)]


def settings_from(values: Sequence[Any]) -> EditSettings:
    """:class:`EditSettings` from the edit controls' values, in :data:`EDIT_FIELDS` order."""
    if len(values) != len(EDIT_FIELDS):
        raise TorchiidError(f"expected {len(EDIT_FIELDS)} edit values, got {len(values)}")
    given = dict(zip(EDIT_FIELDS, values, strict=True))
    defaults = EditSettings()
    for name in ("tint_strength", "intensity", "soften", "hue", "chroma", "scale"):
        given[name] = float(getattr(defaults, name) if given[name] is None else given[name])
    given["merge"], given["flatten"] = bool(given["merge"]), bool(given["flatten"])
    given["tint"] = given["tint"] or defaults.tint
    given["fit"] = given["fit"] or defaults.fit
    given["texture"] = str(given["texture"]) if given["texture"] else None
    return EditSettings(**given)


def _message(exc: BaseException, uploads: dict[str, str]) -> str:
    """The error's one line, with the upload folder's paths replaced by the files' names."""
    text = one_line(str(exc))
    for path, name in uploads.items():
        text = text.replace(path, name)
    return text


def _user_errors(fn: Callable) -> Callable:
    """Turn a callback's errors into one-line messages in the page (``gr.Error``)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        uploads = {str(a): Path(a).name for a in args if isinstance(a, str) and a}
        try:
            return fn(*args, **kwargs)
        except gr.Error:
            raise
        except TorchiidError as exc:
            raise gr.Error(_message(exc, uploads), duration=None, print_exception=False) from None
        except Exception as exc:  # noqa: BLE001 - one line in the page, the traceback in the log
            log.error("torchiid app: %s failed", fn.__name__, exc_info=exc)
            text = unimportable_dependency(exc) or (
                f"internal error ({type(exc).__name__}: {_message(exc, uploads)})"
            )
            raise gr.Error(text, duration=None, print_exception=False) from None

    return wrapper


#: the outputs :meth:`Callbacks.failed` empties, in its order
CLEARED = (
    "session",
    "photo",
    "reflectance",
    "shading",
    "info",
    "compare_view",
    "layers_file",
    "edited_file",
    "gallery",
    "selection",
    "size",
    "status",
)
#: failure messages kept for tabs that have not shown them (an API client shows none)
_FAILURES_KEPT = 64


def _tab(request: gr.Request | None) -> str:
    """The browser tab a call came from (Gradio's session hash), or ``""`` without one."""
    return str(getattr(request, "session_hash", None) or "")


def _no_photo() -> gr.Error:
    return gr.Error("open a photo first", duration=5, print_exception=False)


def _markdown(info: dict[str, Any]) -> str:
    """The run's info as Markdown: sizes, seconds per step and the solvers' reports."""
    w, h = info["size"]
    ww, wh = info["working_size"]
    lines = [
        f"**{info['input']}**: {w}×{h} px ({info['bit_depth']}-bit, EXIF orientation "
        f"{info['exif_orientation']}), decomposed at {ww}×{wh} px, {info['iterations']} "
        f"alternation{'s' if info['iterations'] != 1 else ''}, in {info['seconds']:.1f} s; "
        f"shading white {info['shading_white']:.3g}, "
        f"albedo excess {info['albedo_excess']:.2%}",
        *(
            ["", f"{n} negative values of the file were set to 0."]
            if (n := info.get("negatives_set_to_zero"))
            else []
        ),
        "",
        "| step | seconds |",
        "| --- | --- |",
        *(f"| {name} | {sec:.2f} |" for name, sec in info["times"].items()),
        "",
        "Solvers" + (" (all converged):" if info["converged"] else ":"),
        "",
        *(f"- {line}" for line in info["solves"]),
    ]
    return "\n".join(lines)


class Callbacks:
    """The callbacks of one server: its configuration and its temporary folder.

    Args:
        config: the server's :class:`AppConfig`.
        folder: the server's :class:`~torchiid.app.files.ServerFolder`.
    """

    def __init__(self, config: AppConfig, folder: ServerFolder) -> None:
        self.config = config
        self.folder = folder
        #: the last failed decomposition's message, per tab, until :meth:`failed` shows it
        self._failures: dict[str, str] = {}
        self._failures_lock = threading.Lock()  # decompose and failed run on Gradio's threads

    def decompose(
        self,
        photo: str | None,
        preset: str,
        iterations: float,
        max_side: float,
        previous: Session | None = None,
        request: gr.Request | None = None,
        progress: Any = gr.Progress(),  # noqa: B008 - Gradio's way of asking for a progress bar
    ) -> tuple[Session, np.ndarray, np.ndarray, np.ndarray, str]:
        """Read and decompose the photo: the session, photo, reflectance, shading and info.

        The previous photo's session is forgotten once the new one is open. When the photo
        cannot be decomposed, the error's message is kept for :meth:`failed` (which the page
        calls next) and raised to the page.
        """
        try:
            out = self._decompose(photo, preset, iterations, max_side, previous, progress)
        except gr.Error as err:
            with self._failures_lock:
                self._failures[_tab(request)] = err.message
                while len(self._failures) > _FAILURES_KEPT:  # tabs that never showed theirs
                    self._failures.pop(next(iter(self._failures)))
            raise
        if out[0] is not previous:
            forget(previous)
        return out

    @_user_errors
    def _decompose(
        self,
        photo: str | None,
        preset: str,
        iterations: float,
        max_side: float,
        previous: Session | None,
        progress: Any,
    ) -> tuple[Session, np.ndarray, np.ndarray, np.ndarray, str]:
        if not photo:
            raise gr.Error("choose a photo file first", duration=5, print_exception=False)
        params = Parameters.preset(preset or "default").replace(
            iterations=int(iterations), max_side=int(max_side)
        )
        source = (photo, params)
        if previous is not None and previous.cache.get("source") == source:
            # the same file with the same settings (Decompose pressed while its upload was
            # being decomposed): the result would be the same, so it is not computed again
            return (previous, *self._views(previous))

        def report(fraction: float, message: str) -> None:
            progress(fraction, desc=message)

        session = open_photo(
            photo,
            params,
            name=Path(photo).name,
            device=self.config.device,
            memory_limit=self.config.memory_limit,
            progress=report,
        )
        session.cache["source"] = source
        return (session, *self._views(session))

    def failed(
        self, previous: Session | None, photo: str | None, request: gr.Request | None = None
    ) -> tuple[Any, ...]:
        """After a decomposition failed: no photo open, every output empty, why in the page.

        The outputs of :data:`CLEARED`: the previous photo's session (its files removed), its
        layers, slider, downloads, gallery and selection give way, so that nothing on the page
        belongs to a photo other than the file chosen; the run info names that file and
        repeats the error's message, which stays after its pop-up is closed.
        """
        forget(previous)
        with self._failures_lock:
            text = self._failures.pop(_tab(request), None)
        name = f"**{Path(photo).name}**" if photo else "The photo"
        info = f"{name} could not be decomposed" + (f": {text}" if text else ".")
        size = gr.update(value=0, maximum=1)
        status = "Open a photo, then click an object in it."
        return None, None, None, None, info, None, None, None, [], None, size, status

    @staticmethod
    def _views(session: Session) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        """The photo, reflectance and shading previews and the run info of a session."""
        p = session.preview
        white = float(session.result.shading_white[0])
        return (
            srgb8(p.image),
            srgb8(p.reflectance),
            srgb8(view_shading(p.shading, white)),
            _markdown(session.info),
        )

    @_user_errors
    def details(self, session: Session | None) -> tuple[list, None, Any, str]:
        """After a decomposition: the gallery, no selection, the size slider, the hint."""
        if session is None:
            raise _no_photo()
        hint = "Click an object in the photo to select it."
        return session.gallery, None, gr.update(value=0, maximum=1), hint

    @_user_errors
    def layers_zip(self, session: Session | None) -> str:
        """Write the layers (the CLI's files) as a zip; its path."""
        if session is None:
            raise _no_photo()
        return str(write_layers_zip(session, self._downloads(session)))

    @_user_errors
    def preview(
        self, session: Session | None, selection: Selection | None, compare: str, *values: Any
    ) -> tuple[np.ndarray, np.ndarray] | Any:
        """The edits at the preview resolution: ``(photo, edited view)`` for the slider.

        Before a photo is open the controls can move: nothing changes then.
        """
        if session is None:
            return gr.skip()
        settings = settings_from(values)
        proposal = None if selection is None else selection.proposal
        if proposal is None and settings.object_edits and not session.cache.get("told_select"):
            session.cache["told_select"] = True  # once per photo: the controls say the rest
            gr.Info(
                "Hue, chroma, flattening and a new albedo change the selected object: "
                "click one in the photo",
                duration=8,
            )
        edited = render(session, settings, proposal)
        white = float(session.result.shading_white[0])
        shown = {
            COMPARE[0]: edited.image,
            COMPARE[1]: edited.reflectance,
            COMPARE[2]: view_shading(edited.shading, white),
        }[compare if compare in COMPARE else COMPARE[0]]
        return srgb8(session.preview.image), srgb8(shown)

    @_user_errors
    def select(
        self, session: Session | None, evt: gr.SelectData
    ) -> tuple[Selection, np.ndarray, Any, str]:
        """A click on the photo: the objects under it, the smallest selected."""
        if session is None or session.objects is None:
            raise _no_photo()
        h, w = session.preview.size
        x, y = evt.index[0], evt.index[1]
        candidates = session.objects.under((x + 0.5) / w, (y + 0.5) / h)
        if not candidates:
            return (
                None,
                srgb8(session.preview.image),
                gr.update(value=0, maximum=1),
                "No object there; click elsewhere.",
            )
        selection = Selection(tuple(candidates))
        image, status = self._selected(session, selection)
        return selection, image, gr.update(value=0, maximum=max(len(candidates) - 1, 1)), status

    @_user_errors
    def resize_selection(
        self, session: Session | None, selection: Selection | None, index: float
    ) -> tuple[Selection | None, np.ndarray, str]:
        """The size slider: a larger or smaller object under the same click."""
        if session is None:
            raise _no_photo()
        if selection is None:
            return None, srgb8(session.preview.image), "Click an object in the photo first."
        selection = Selection(selection.candidates, int(index))
        image, status = self._selected(session, selection)
        return selection, image, status

    def clear_selection(self, session: Session | None) -> tuple[None, Any, Any, str]:
        """Forget the selection: the photo as it is, the size slider back at the smallest."""
        image = None if session is None else srgb8(session.preview.image)
        size = gr.update(value=0, maximum=1)
        return None, image, size, "Click an object in the photo to select it."

    @_user_errors
    def check_albedo(self, session: Session | None, path: str | None) -> str | None:
        """A new albedo file as it is uploaded: kept if it reads, else removed with a warning.

        A file that cannot be read would otherwise stay in its box and fail every later edit.
        """
        if not path:
            return path
        try:
            # read once: kept in the photo's session, where the preview takes it from
            load_texture(path) if session is None else texture_of(session, path)
        except TorchiidError as exc:
            gr.Warning(f"{_message(exc, {path: Path(path).name})}; it is not used", duration=10)
            return None
        return path

    def _selected(self, session: Session, selection: Selection) -> tuple[np.ndarray, str]:
        h, w = session.preview.size
        mask = session.objects.mask(selection.proposal, (h, w))
        share = float(mask.float().mean())
        i, n = min(selection.index, len(selection.candidates) - 1) + 1, len(selection.candidates)
        status = f"Selected: {share:.1%} of the photo (object {i} of {n} under the click)."
        return highlight(srgb8(session.preview.image), mask), status

    @_user_errors
    def full_resolution(
        self,
        session: Session | None,
        selection: Selection | None,
        *values: Any,
        progress: Any = gr.Progress(),  # noqa: B008
    ) -> str:
        """The edited photo at full resolution, as a PNG file; its path."""
        if session is None:
            raise _no_photo()
        settings = settings_from(values)
        progress(0.1, desc="editing at full resolution")
        proposal = None if selection is None else selection.proposal
        edited = render(session, settings, proposal, full=True)
        progress(0.8, desc="writing the PNG")
        return str(write_edited(session, edited.image, self._downloads(session)))

    def _downloads(self, session: Session) -> Path:
        """The session's download folder, made when it first writes one."""
        if session.cache.get("folder") is None:
            session.cache["folder"] = self.folder.session_folder()
        return session.cache["folder"]


def forget(session: Session | None) -> None:
    """Remove a session's files (its downloads): a new photo replaces it, or its tab closed."""
    if session is not None and session.cache.get("folder") is not None:
        shutil.rmtree(session.cache.pop("folder"), ignore_errors=True)
