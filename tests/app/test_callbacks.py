"""The page's callbacks called as plain functions: outputs, downloads and error messages."""

from __future__ import annotations

import gc
import json
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

gr = pytest.importorskip("gradio")

import torchiid.app.callbacks as callbacks  # noqa: E402
from torchiid.app.callbacks import (  # noqa: E402
    CLEARED,
    COMPARE,
    EDIT_FIELDS,
    Callbacks,
    Selection,
    forget,
    settings_from,
)
from torchiid.app.config import AppConfig  # noqa: E402
from torchiid.app.edits import EditSettings  # noqa: E402
from torchiid.app.files import ServerFolder, layer_names  # noqa: E402
from torchiid.cli import main  # noqa: E402
from torchiid.io import load_image  # noqa: E402

DEFAULTS = [getattr(EditSettings(), name) for name in EDIT_FIELDS]


@pytest.fixture
def calls(tmp_path):
    folder = ServerFolder(tmp_path)
    yield Callbacks(AppConfig(iterations=1), folder)
    folder.remove()


def _values(**changes) -> list:
    return [changes.get(name, value) for name, value in zip(EDIT_FIELDS, DEFAULTS, strict=True)]


def _click(x: int, y: int):
    return gr.SelectData(None, {"index": [x, y], "value": None})


def test_decompose_returns_the_session_the_three_views_and_the_run_info(calls, photos):
    seen = []
    out = calls.decompose(
        str(photos["chelsea"]), "default", 1, 512, None, progress=lambda f, desc: seen.append(desc)
    )
    session, photo, refl, shading, info = out
    assert session.name == "chelsea.png"
    for view in (photo, refl, shading):
        assert view.shape == (150, 200, 3) and view.dtype == np.uint8
    assert (shading[..., 0] == shading[..., 1]).all()  # the shading is gray
    assert np.abs(refl.astype(int) - photo.astype(int)).mean() > 5
    assert "**chelsea.png**: 200×150 px" in info and "1 alternation," in info
    assert "| total |" in info and "- shading 1:" in info
    assert seen[0] == "reading the photo" and "alternation 1 of 1" in seen


@pytest.mark.parametrize(
    "name, expected",
    [
        ("text", "notes.txt: is not an image"),
        ("truncated", "truncated.jpg: is truncated or corrupt"),
        ("tiny", "tiny.png: is 1x1 px; at least 60 px per side is needed"),
    ],
)
def test_a_bad_file_is_a_one_line_message_naming_it(calls, photos, name, expected):
    with pytest.raises(gr.Error) as err:
        calls.decompose(str(photos[name]), "default", 1, 512)
    message = err.value.message
    assert message.startswith(expected) and "\n" not in message
    assert str(photos[name].parent) not in message  # the file's name, not the upload folder
    assert err.value.duration is None  # it stays until it is closed


def test_a_photo_over_the_memory_limit_says_the_limit_and_how_to_raise_it(tmp_path, photos):
    folder = ServerFolder(tmp_path)
    calls = Callbacks(AppConfig(memory_limit=100_000_000), folder)
    with pytest.raises(gr.Error) as err:
        calls.decompose(str(photos["small"]), "default", 1, 512)
    message = err.value.message
    assert "96x64 px at full resolution needs about" in message
    assert "over the memory limit of 0.10 GB" in message and "--memory-limit GB" in message
    folder.remove()


def test_a_large_declared_size_is_refused_before_the_pixels_are_decoded(
    tmp_path, photos, monkeypatch
):
    import torchiid.app.session as session_module

    def never(*args, **kwargs):
        raise AssertionError("decoded")

    monkeypatch.setattr(session_module, "load_image", never)
    folder = ServerFolder(tmp_path)
    calls = Callbacks(AppConfig(memory_limit=1_000_000_000), folder)
    with pytest.raises(gr.Error) as err:
        calls.decompose(str(photos["declared"]), "default", 1, 512)
    message = err.value.message
    assert message.startswith("declared.png: decomposing 30000x20000 px at 512x341 px needs")
    assert "over the memory limit of 1.00 GB" in message
    folder.remove()


def test_a_memory_message_speaks_of_the_page_s_controls(monkeypatch):
    import torchiid.pipeline.memory as memory
    from torchiid.app.session import _app_terms
    from torchiid.core.exceptions import MemoryLimitError
    from torchiid.params import Parameters

    # the library's own message, for a machine with 2 GB left
    monkeypatch.setattr(memory, "available_memory", lambda: 2_000_000_000)
    with pytest.raises(MemoryLimitError) as err:
        memory.check_memory(6000, 9000, Parameters().replace(max_side=0))
    said = _app_terms(str(err.value))
    assert "with a working resolution of 512 px, it needs about" in said
    assert said.endswith("; a photo of fewer pixels needs less")
    assert "TORCHIID_MEMORY_CHECK" not in said and "--max-side" not in said


def test_a_working_resolution_too_small_for_the_patches_says_what_to_set(calls, photos):
    with pytest.raises(gr.Error) as err:
        calls.decompose(str(photos["panorama"]), "default", 1, 512)
    assert err.value.message == (
        "panorama.png: at a working resolution of 512 px the photo is 512x34 px, under the 60 "
        "px the method needs on each side; set the working resolution to 900 px or more, or to "
        "0 (the photo's own size)"
    )


def test_a_new_albedo_that_cannot_be_read_is_removed_with_a_warning(calls, photos):
    session = calls.decompose(str(photos["small"]), "default", 1, 512)[0]
    for where in (None, session):
        with pytest.warns(UserWarning, match=r"new albedo: notes\.txt: is not an image"):
            assert calls.check_albedo(where, str(photos["text"])) is None
        assert calls.check_albedo(where, str(photos["texture"])) == str(photos["texture"])
        assert calls.check_albedo(where, None) is None
    # read once, into the session the preview takes it from
    assert ("texture", str(photos["texture"])) in session.cache


def test_an_albedo_error_names_the_control(calls, chelsea_session, photos):
    values = _values(texture=str(photos["text"]))
    selection = Selection((0,))
    with pytest.raises(gr.Error) as err:
        calls.preview(chelsea_session, selection, COMPARE[0], *values)
    assert err.value.message.startswith("new albedo: notes.txt: is not an image")


def test_object_edits_without_a_selection_say_once_how_to_select(calls, photos, monkeypatch):
    told = []
    monkeypatch.setattr(callbacks.gr, "Info", lambda message, **kwargs: told.append(message))
    session = calls.decompose(str(photos["small"]), "default", 1, 512)[0]
    calls.preview(session, None, COMPARE[0], *_values(soften=0.5))
    assert told == []  # a light edit needs no selection
    for hue in (30, 60):
        calls.preview(session, None, COMPARE[0], *_values(hue=hue))
    assert len(told) == 1 and "click one in the photo" in told[0]


def test_the_same_file_with_the_same_settings_is_not_decomposed_again(calls, photos, monkeypatch):
    first = calls.decompose(str(photos["small"]), "default", 1, 512)
    runs = []
    real = callbacks.open_photo
    monkeypatch.setattr(callbacks, "open_photo", lambda *a, **k: runs.append(a) or real(*a, **k))
    again = calls.decompose(str(photos["small"]), "default", 1, 512, first[0])
    assert runs == [] and again[0] is first[0]
    assert all((a == b).all() for a, b in zip(again[1:4], first[1:4], strict=True))
    other = calls.decompose(str(photos["small"]), "default", 2, 512, first[0])
    assert len(runs) == 1 and other[0] is not first[0] and "2 alternations" in other[4]


class _Tab:
    """What Gradio passes as ``gr.Request``: the tab's session hash is all the callbacks read."""

    def __init__(self, session_hash: str) -> None:
        self.session_hash = session_hash


def test_a_failed_photo_clears_the_page_and_says_why_in_it(calls, photos):
    first = calls.decompose(str(photos["small"]), "default", 1, 512, request=_Tab("a"))[0]
    folder = calls._downloads(first)
    zip_path = calls.layers_zip(first)
    with pytest.raises(gr.Error) as err:
        calls.decompose(str(photos["text"]), "default", 1, 512, first, request=_Tab("a"))
    # the previous photo stays whole until the page takes the failure (an API call keeps it)
    assert folder.is_dir() and first.cache["folder"] == folder
    other_tab = calls.failed(None, str(photos["text"]), request=_Tab("b"))
    assert other_tab[CLEARED.index("info")] == "**notes.txt** could not be decomposed."
    out = calls.failed(first, str(photos["text"]), request=_Tab("a"))
    assert len(out) == len(CLEARED)
    shown = dict(zip(CLEARED, out, strict=True))
    assert shown["info"] == f"**notes.txt** could not be decomposed: {err.value.message}"
    assert err.value.message.startswith("notes.txt: is not an image")
    for name in ("session", "photo", "reflectance", "shading", "compare_view", "layers_file"):
        assert shown[name] is None, name
    assert shown["edited_file"] is None and shown["selection"] is None and shown["gallery"] == []
    assert shown["size"]["value"] == 0 and "Open a photo" in shown["status"]
    assert not folder.exists() and not Path(zip_path).exists()  # its downloads removed
    # the message is shown once: a later failure without one says only that it failed
    assert calls.failed(None, None, request=_Tab("a"))[4] == "The photo could not be decomposed."


def test_a_new_photo_replaces_the_previous_one_s_files_once_it_is_open(calls, photos):
    first = calls.decompose(str(photos["small"]), "default", 1, 512)[0]
    folder = calls._downloads(first)
    second = calls.decompose(str(photos["chelsea"]), "default", 1, 512, first)[0]
    assert second is not first and not folder.exists()
    forget(second)


def test_failure_messages_kept_for_tabs_that_never_show_them_are_bounded(calls, photos):
    for i in range(callbacks._FAILURES_KEPT + 5):
        with pytest.raises(gr.Error):
            calls.decompose(None, "default", 1, 512, request=_Tab(f"tab{i}"))
    assert len(calls._failures) == callbacks._FAILURES_KEPT
    assert "tab0" not in calls._failures and f"tab{callbacks._FAILURES_KEPT + 4}" in calls._failures


def test_clearing_the_selection_puts_the_size_slider_back(calls, chelsea_session):
    selection, image, size, status = calls.clear_selection(chelsea_session)
    assert selection is None and image.shape == (150, 200, 3)
    assert size["value"] == 0 and "Click an object" in status


def test_no_photo_and_bad_settings_are_messages_too(calls, photos):
    with pytest.raises(gr.Error, match="choose a photo file first"):
        calls.decompose(None, "default", 1, 512)
    with pytest.raises(gr.Error, match="unknown preset 'nope'"):
        calls.decompose(str(photos["small"]), "nope", 1, 512)
    with pytest.raises(gr.Error, match="iterations must be > 0"):
        calls.decompose(str(photos["small"]), "default", 0, 512)


def test_an_unexpected_error_is_one_line_too(calls, chelsea_session, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("the GPU caught fire\nsecond line")

    monkeypatch.setattr(callbacks, "render", broken)
    with pytest.raises(gr.Error) as err:
        calls.preview(chelsea_session, None, COMPARE[0], *DEFAULTS)
    assert err.value.message == "internal error (RuntimeError: the GPU caught fire second line)"


def test_a_library_that_cannot_be_imported_is_named_in_the_page(
    calls, chelsea_session, monkeypatch, tmp_path
):
    (tmp_path / "brokenlib.py").write_text('raise ImportError("libbroken.so: not found")\n')
    monkeypatch.syspath_prepend(str(tmp_path))

    def needs_it(*args, **kwargs):
        import brokenlib  # noqa: F401

    monkeypatch.setattr(callbacks, "render", needs_it)
    with pytest.raises(gr.Error) as err:
        calls.preview(chelsea_session, None, COMPARE[0], *DEFAULTS)
    assert err.value.message == (
        "brokenlib is installed but cannot be imported (libbroken.so: not found); "
        "reinstall it: pip install --force-reinstall --no-deps brokenlib"
    )


def test_preview_compares_the_photo_with_the_edited_layers(calls, chelsea_session):
    s = chelsea_session
    before, after = calls.preview(s, None, COMPARE[0], *DEFAULTS)
    assert before.shape == after.shape == (150, 200, 3)
    assert np.abs(before.astype(int) - after.astype(int)).max() <= 1  # nothing edited
    _, softer = calls.preview(s, None, COMPARE[0], *_values(soften=0.9))
    assert softer.mean() > before.mean() + 5
    _, refl = calls.preview(s, None, COMPARE[1], *DEFAULTS)
    _, shading = calls.preview(s, None, COMPARE[2], *DEFAULTS)
    assert (shading[..., 0] == shading[..., 1]).all() and not (refl == before).all()
    assert calls.preview(None, None, COMPARE[0], *DEFAULTS) == gr.skip()  # no photo yet
    with pytest.raises(gr.Error, match="cannot read the colour"):
        calls.preview(s, None, COMPARE[0], *_values(tint="warmish", tint_strength=0.5))


def test_a_click_selects_the_object_under_it_and_the_size_slider_grows_it(calls, chelsea_session):
    s = chelsea_session
    selection, photo, size, status = calls.select(s, _click(100, 75))
    assert isinstance(selection, Selection) and len(selection.candidates) >= 2
    assert size["maximum"] == len(selection.candidates) - 1 and size["value"] == 0
    assert status.startswith("Selected: ") and "object 1 of" in status
    assert photo.shape == (150, 200, 3) and photo.mean() < callbacks.srgb8(s.preview.image).mean()
    shares = []
    for i in range(len(selection.candidates)):
        selection, _, status = calls.resize_selection(s, selection, i)
        shares.append(float(status.split()[1].rstrip("%")))
    assert shares == sorted(shares) and shares[-1] > shares[0]
    # a hue edit changes the selected object only
    small = Selection(selection.candidates, 0)
    _, before = calls.preview(s, None, COMPARE[0], *_values(hue=150))
    _, after = calls.preview(s, small, COMPARE[0], *_values(hue=150))
    mask = s.objects.mask(small.proposal, s.preview.size)[0, 0].numpy()
    changed = np.abs(before.astype(int) - after.astype(int)).max(-1) > 2
    assert changed[mask].mean() > 0.5 and not changed[~mask].any()
    cleared, photo, _, status = calls.clear_selection(s)
    assert cleared is None and (photo == callbacks.srgb8(s.preview.image)).all()


def test_the_layers_zip_holds_the_files_the_cli_writes(calls, chelsea_session, photos, tmp_path):
    zip_path = calls.layers_zip(chelsea_session)
    assert zip_path.endswith("chelsea-layers.zip")
    with zipfile.ZipFile(zip_path) as zf:
        names = zf.namelist()
        zf.extractall(tmp_path / "app")
    assert names == layer_names("chelsea")
    out = tmp_path / "cli"
    argv = ["decompose", str(photos["chelsea"]), "-o", str(out), "--save-stage1"]
    assert main([*argv, "--iterations", "2", "--no-progress"]) == 0
    cli_names = sorted(p.name for p in out.iterdir() if p.name != "manifest.jsonl")
    assert sorted(names) == cli_names
    # the same decomposition: the exact reflectance is the CLI's, code for code
    for name in ("chelsea-reflectance-linear16.png", "chelsea-shading.png"):
        app = cv2.imread(str(tmp_path / "app" / name), cv2.IMREAD_UNCHANGED)
        cli = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(app, cli), name
    info = json.loads((tmp_path / "app" / "chelsea-info.json").read_text())
    assert info["written_by"] == "torchiid app" and "chelsea-sigma.exr" in info["files"]
    folder = chelsea_session.cache["folder"]
    assert folder.parent == calls.folder.sessions
    forget(chelsea_session)
    assert not folder.exists()


def test_the_edited_photo_comes_at_full_resolution(calls, photos):
    session = calls.decompose(str(photos["coffee"]), "default", 1, 150)[0]
    assert session.preview.size == (100, 150)
    path = calls.full_resolution(session, None, *_values(soften=0.5))
    assert path.endswith("coffee600-edited.png")
    edited = load_image(path).image
    assert edited.shape == (3, 400, 600)
    assert float(edited.mean()) > float(session.full.image.mean()) + 0.02
    plain = load_image(calls.full_resolution(session, None, *DEFAULTS)).image
    assert float((plain - session.full.image).abs().max()) < 0.01  # 8-bit rounding
    folder = session.cache["folder"]
    forget(session)
    assert not folder.exists()


def test_settings_from_the_controls_values():
    s = settings_from(_values(hue=30, merge=0, texture="/x/t.png", tint=None, scale=None))
    assert s == EditSettings(merge=False, hue=30.0, texture="/x/t.png")
    with pytest.raises(Exception, match="expected 11 edit values"):
        settings_from([1, 2])


# Building a page outside a server leaves event loops that Gradio opens and never closes;
# they are collected inside this test so that no later test reports them.
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_the_previews_run_one_at_a_time_in_the_order_the_controls_moved(tmp_path):
    # Two previews at once could finish out of order: one started before the last move (the
    # one chained after a selection, say) would land last and show edits the controls no
    # longer have. One shared group of one runs them first in, first out.
    from torchiid.app.ui import build_app

    folder = ServerFolder(tmp_path)
    try:
        demo = build_app(AppConfig(iterations=1), folder)
        previews = [f for f in demo.fns.values() if f.name == "preview"]
        del demo
        assert len(previews) > 10  # every control, the compare choice, select, size, reset...
        assert {f.concurrency_id for f in previews} == {"edit"}
        assert {f.concurrency_limit for f in previews} == {1}
        assert {f.trigger_mode for f in previews} == {"always_last"}
    finally:
        previews = []
        gc.collect()
        folder.remove()
