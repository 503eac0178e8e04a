"""The page in a real browser (Playwright driving headless Chromium) against ``torchiid app``.

Upload a photo, wait for its layers, move a slider, click an object, download the layers and
the edited photo; every bad input gets its message in the page and the page stays usable; two
tabs at once. With ``TORCHIID_UPDATE_SCREENSHOT=1`` the first test decomposes the 600x400
coffee photo with 5 alternations and writes the README's screenshot, ``docs/images/app.jpg``.
"""

from __future__ import annotations

import os
import time
import zipfile
from pathlib import Path

import pytest
from PIL import Image

pytest.importorskip("gradio")
playwright = pytest.importorskip("playwright.sync_api")

from torchiid.app.files import layer_names  # noqa: E402

expect = playwright.expect

SCREENSHOT = Path(__file__).resolve().parents[2] / "docs" / "images" / "app.jpg"
#: seconds a decomposition of a small photo may take on a busy machine
DECOMPOSE_TIMEOUT = 180_000

#: records every progress text the page shows, in order (the progress bar's steps are brief)
WATCH_PROGRESS = """() => {
  window.__progress = [];
  new MutationObserver(() => {
    document.querySelectorAll('.progress-text, .progress-level-inner, .meta-text').forEach(e => {
      const t = e.innerText.trim();
      if (t && !window.__progress.includes(t)) window.__progress.push(t);
    });
  }).observe(document.body, {subtree: true, childList: true, characterData: true});
}"""


def _open(page, url: str, photo: Path) -> None:
    """Upload a photo into the page (clearing the previous one first)."""
    clear = page.locator("#photo-file button[aria-label='Clear']")
    if clear.count():
        clear.first.click()
    page.set_input_files("#photo-file input[type=file]", str(photo))


def _after(page) -> str:
    """The source of the slider's "after" image."""
    return page.locator("#compare img").nth(1).get_attribute("src") or ""


def _set(page, elem_id: str, value: float) -> None:
    """Type a value into a slider's number box, as a user does, and leave the box."""
    box = page.locator(f"#{elem_id} input[type=number]")
    box.fill(str(value))
    box.press("Enter")


def _click_image(page, elem_id: str, u: float, v: float) -> None:
    """Click at ``(u, v)`` (fractions of the width and height) of the picture an image shows.

    Gradio draws a picture at most at its own size, centred in its box, and takes only
    clicks on the picture.
    """
    img = page.locator(f"#{elem_id} img")
    box = img.bounding_box()
    natural = img.evaluate("i => [i.naturalWidth, i.naturalHeight]")
    scale = min(box["width"] / natural[0], box["height"] / natural[1], 1)
    x = (box["width"] - natural[0] * scale) / 2 + u * natural[0] * scale
    y = (box["height"] - natural[1] * scale) / 2 + v * natural[1] * scale
    img.click(position={"x": x, "y": y})


def _wait_for_new_after(page, before: str, server) -> None:
    """Wait for the slider's "after" image to change; if it does not, say what the page and
    the server showed."""
    try:
        page.wait_for_function(
            "(b) => { const i = document.querySelectorAll('#compare img')[1];"
            " return i && i.getAttribute('src') !== b; }",
            arg=before,
            timeout=60_000,
        )
    except playwright.Error:
        toasts = page.locator(".toast-body").all_inner_texts()
        status = page.locator("#selection-status").inner_text()
        log = "".join(server.stderr)[-3000:]
        pytest.fail(f"the preview did not change; page: {toasts} {status!r}; server:\n{log}")


def _settled_after(page, quiet: float = 2.0, timeout: float = 60.0) -> str:
    """The "after" image's source once it has not changed for ``quiet`` seconds: every
    preview still queued has landed."""
    deadline = time.monotonic() + timeout
    last, since = _after(page), time.monotonic()
    while time.monotonic() < deadline:
        page.wait_for_timeout(250)
        now = _after(page)
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet:
            return last
    pytest.fail(f"the preview was still changing after {timeout:.0f} s")


def test_upload_slider_click_and_downloads(page, browser_app, photos, tmp_path):
    screenshot = os.environ.get("TORCHIID_UPDATE_SCREENSHOT") == "1"
    photo = photos["coffee"] if screenshot else photos["small"]
    requests: list[str] = []
    page.on("request", lambda request: requests.append(request.url))
    page.goto(browser_app.url)
    if screenshot:
        _set(page, "iterations", 5)
    page.evaluate(WATCH_PROGRESS)
    _open(page, browser_app.url, photo)
    expect(page.locator("#layers-zip a")).to_be_visible(timeout=DECOMPOSE_TIMEOUT)
    for view in ("photo", "reflectance", "shading"):
        expect(page.locator(f"#{view} img")).to_be_visible()
    expect(page.locator("#info")).to_contain_text(f"{photo.name}: ")
    progress = page.evaluate("window.__progress")
    assert any("Stage 0: semantic features" in t for t in progress), progress
    assert any("alternation 1 of" in t for t in progress), progress

    # a slider: the preview changes
    before = _after(page)
    _set(page, "soften", 0.3)
    _wait_for_new_after(page, before, browser_app)

    # a click on the object under the pointer selects it; a hue edit recolours it
    _click_image(page, "photo", 0.72, 0.78)
    status = page.locator("#selection-status")
    expect(status).to_contain_text("Selected: ", timeout=60_000)
    expect(status).to_contain_text("(object 1 of ")
    # the size slider: a larger object under the same click
    _set(page, "selection-size", 1)
    expect(status).to_contain_text("(object 2 of ", timeout=60_000)
    if screenshot:
        _set(page, "selection-size", 5)
        expect(status).to_contain_text("(object 6 of ", timeout=60_000)
    # every preview so far leaves the object edits at their defaults, so ``before`` is the
    # same picture (the same file) whether or not the one that follows the size change
    # has landed yet; that one must not land after the hue's and hide it
    before = _after(page)
    _set(page, "hue", 150)
    _wait_for_new_after(page, before, browser_app)
    assert _settled_after(page) != before

    # every alternation's layers
    page.get_by_text("Every alternation's layers").click()
    expect(page.locator("#iterations-gallery img").first).to_be_visible()

    # the layers, as the CLI writes them
    with page.expect_download() as download:
        page.locator("#layers-zip a").first.click()
    assert download.value.suggested_filename == f"{photo.stem}-layers.zip"
    zip_path = tmp_path / "layers.zip"
    download.value.save_as(zip_path)
    with zipfile.ZipFile(zip_path) as zf:
        assert zf.namelist() == layer_names(photo.stem)

    # the edited photo at full resolution
    page.locator("#render-full").click()
    expect(page.locator("#edited-file a")).to_be_visible(timeout=DECOMPOSE_TIMEOUT)
    with page.expect_download() as download:
        page.locator("#edited-file a").first.click()
    edited = tmp_path / "edited.png"
    download.value.save_as(edited)
    with Image.open(edited) as got, Image.open(photo) as original:
        assert got.size == original.size

    # the page loaded nothing from anywhere but the server (no fonts, no analytics)
    outside = [u for u in requests if not u.startswith((browser_app.url, "data:", "blob:"))]
    assert outside == []

    if screenshot:
        page.get_by_text("Every alternation's layers").click()  # folded again
        page.set_viewport_size({"width": 1280, "height": 1480})
        page.evaluate("window.scrollTo(0, 0)")
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOT), type="jpeg", quality=70)


@pytest.mark.parametrize(
    "name, message",
    [
        ("text", "notes.txt: is not an image"),
        ("truncated", "truncated.jpg: is truncated or corrupt"),
        ("tiny", "tiny.png: is 1x1 px; at least 60 px per side is needed"),
        ("huge", "huge.jpg: decomposing 3000x2000 px at 512x341 px needs about"),
    ],
)
def test_a_bad_input_gets_a_message_and_the_page_stays_usable(
    page, browser_app, photos, name, message
):
    page.goto(browser_app.url)
    _open(page, browser_app.url, photos[name])
    toast = page.locator(".toast-body.error").last
    expect(toast).to_contain_text(message, timeout=60_000)
    if name == "huge":
        expect(toast).to_contain_text("over the memory limit of")
        expect(toast).to_contain_text("--memory-limit GB")
    assert "Traceback" not in page.content()
    toast.locator(".toast-close").click()
    _open(page, browser_app.url, photos["small"])
    expect(page.locator("#layers-zip a")).to_be_visible(timeout=DECOMPOSE_TIMEOUT)
    expect(page.locator("#info")).to_contain_text("coffee.png: ")


def test_a_failed_photo_takes_the_previous_one_s_results_off_the_page(page, browser_app, photos):
    page.goto(browser_app.url)
    _open(page, browser_app.url, photos["small"])
    expect(page.locator("#layers-zip a")).to_be_visible(timeout=DECOMPOSE_TIMEOUT)
    expect(page.locator("#compare img")).to_have_count(2, timeout=60_000)
    _open(page, browser_app.url, photos["text"])
    expect(page.locator(".toast-body.error").last).to_contain_text("notes.txt: is not an image")
    info = page.locator("#info")
    expect(info).to_contain_text("notes.txt could not be decomposed: notes.txt: is not an image")
    # nothing of coffee.png is left: no layers, no slider, no zip, no error badges on them
    for elem_id in ("photo", "reflectance", "shading", "compare"):
        expect(page.locator(f"#{elem_id} img")).to_have_count(0)
        expect(page.locator(f"#{elem_id}")).not_to_contain_text("Error")
    expect(page.locator("#layers-zip a")).to_have_count(0)
    assert "coffee.png" not in info.inner_text()
    _open(page, browser_app.url, photos["small"])
    expect(page.locator("#layers-zip a")).to_be_visible(timeout=DECOMPOSE_TIMEOUT)
    expect(info).to_contain_text("coffee.png: ")


def test_two_tabs_at_once_each_get_their_own_photo(context, browser_app, photos):
    tabs = [context.new_page(), context.new_page()]
    for tab in tabs:
        tab.goto(browser_app.url)
    # both start before either ends: the second waits in Gradio's queue
    for tab, name in zip(tabs, ("small", "chelsea"), strict=True):
        _open(tab, browser_app.url, photos[name])
    for tab, name in zip(tabs, ("coffee.png", "chelsea.png"), strict=True):
        expect(tab.locator("#layers-zip a")).to_be_visible(timeout=DECOMPOSE_TIMEOUT)
        expect(tab.locator("#info")).to_contain_text(f"{name}: ")
