"""How fast the app's edits update the preview: callback times, and a browser's round trip.

For photos of 0.24 and 12 megapixels (skimage's coffee, and a 4032x3024 mosaic of four
skimage photos saved as a JPEG) decomposed once (1 alternation: the layers' sizes, not their
quality, set the edits' cost), every edit control of the page is timed as its callback
(:meth:`torchiid.app.callbacks.Callbacks.preview`: the edits on the preview layers and the
sRGB views) and with the JPEG encoding Gradio then does of the slider's two views; the click
on an object, and the downloads (full-resolution edit, the layers' zip) for reference. The
median of ``--repeats`` runs, in milliseconds (the downloads: one run).

With ``--browser`` (needs Debian's Chromium at /usr/bin/chromium and Playwright) the page is
served in this process and driven by headless Chromium: the time from typing a slider value
to the new preview image in the page, the whole round trip a user waits for.

    python tools/bench_app.py                  # callbacks, 0.24 and 12 MP
    python tools/bench_app.py --browser        # and the browser's round trip
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from skimage import data

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_photo_sizes import mosaic  # noqa: E402

import torchiid.app.offline  # noqa: E402, F401 - before Gradio
from torchiid.app.callbacks import COMPARE, EDIT_FIELDS, Callbacks  # noqa: E402
from torchiid.app.config import AppConfig  # noqa: E402
from torchiid.app.edits import EditSettings  # noqa: E402
from torchiid.app.files import ServerFolder  # noqa: E402

#: one row per control: what moving it sets
EDITS = {
    "no edit (merged layers)": {},
    "soften shadows 0.5": {"soften": 0.5},
    "light intensity 0.5": {"intensity": 0.5},
    "light colour #3366ff 0.6": {"tint": "#3366ff", "tint_strength": 0.6},
    "object hue 120": {"hue": 120.0},
    "object flattened": {"flatten": True},
    "object albedo (texture)": {"texture": "TEXTURE"},
    "all of them": {"soften": 0.5, "intensity": 0.5, "tint_strength": 0.6, "hue": 120.0},
}
CHROMIUM = Path("/usr/bin/chromium")


def _values(changes: dict, texture: str) -> list:
    d = EditSettings()
    out = [changes.get(name, getattr(d, name)) for name in EDIT_FIELDS]
    return [texture if v == "TEXTURE" else v for v in out]


def _ms(fn, repeats: int) -> float:
    fn()  # warm-up: caches (merged layers, textures), first-call costs
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def _encode(cache: str, *views: np.ndarray) -> None:
    """What Gradio does with the slider's two views: JPEG files in its cache."""
    from gradio import processing_utils

    for view in views:
        processing_utils.save_img_array_to_cache(view, cache, format="jpeg")


def bench_callbacks(photo: Path, texture: str, repeats: int) -> None:
    folder = ServerFolder()
    calls = Callbacks(AppConfig(iterations=1), folder)
    try:
        session = calls.decompose(
            str(photo), "default", 1, 512, None, progress=lambda *a, **k: None
        )[0]
        h, w = session.full.size
        ph, pw = session.preview.size
        print(f"\n{photo.name}: {w}x{h} px, preview (working resolution) {pw}x{ph} px\n")
        print("| control | callback ms | with Gradio's encoding of the views ms |")
        print("| --- | --- | --- |")
        selection = calls.select(session, _click(pw // 2, ph // 2))[0]
        for name, changes in EDITS.items():
            values = _values(changes, texture)

            def run(values=values):
                return calls.preview(session, selection, COMPARE[0], *values)

            def run_and_encode(values=values):
                _encode(str(folder.gradio), *calls.preview(session, selection, COMPARE[0], *values))

            print(f"| {name} | {_ms(run, repeats):.0f} | {_ms(run_and_encode, repeats):.0f} |")
        click = _ms(lambda: calls.select(session, _click(pw // 3, ph // 2)), repeats)
        print(f"| click on an object | {click:.0f} | |")
        every = _values(EDITS["all of them"], texture)
        full = _ms(lambda: calls.full_resolution(session, selection, *every), 1)
        zipped = _ms(lambda: calls.layers_zip(session), 1)
        print(f"| download: edited photo at {w}x{h} | {full:.0f} | |")
        print(f"| download: the layers' zip | {zipped:.0f} | |")
    finally:
        folder.remove()


def _click(x: int, y: int):
    import gradio as gr

    return gr.SelectData(None, {"index": [x, y], "value": None})


def bench_browser(photo: Path, repeats: int) -> None:
    from playwright.sync_api import sync_playwright

    from torchiid.app.server import Server

    args = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]
    args += ["--disable-component-update", "--disable-sync", "--no-first-run"]
    with Server(AppConfig(iterations=1)) as server, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=args)
        page = browser.new_page(viewport={"width": 1280, "height": 1000})
        page.goto(server.url)
        page.set_input_files("#photo-file input[type=file]", str(photo))
        page.wait_for_selector("#layers-zip a", timeout=600_000)
        box = page.locator("#soften input[type=number]")
        times = []
        for i in range(repeats + 1):
            before = page.locator("#compare img").nth(1).get_attribute("src")
            t0 = time.perf_counter()
            box.fill(f"{0.2 + 0.05 * (i % 10):.2f}")
            box.press("Enter")
            page.wait_for_function(
                "(b) => document.querySelectorAll('#compare img')[1].getAttribute('src') !== b",
                arg=before,
                timeout=60_000,
            )
            times.append(time.perf_counter() - t0)
        browser.close()
    ms = 1000 * statistics.median(times[1:])
    print(f"\nbrowser, {photo.name}: slider value typed -> new preview shown: {ms:.0f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--browser", action="store_true", help="also the browser's round trip")
    args = parser.parse_args()
    print(f"torch threads: {torch.get_num_threads()}")
    with tempfile.TemporaryDirectory() as tmp:
        photos = [Path(tmp) / "coffee.png", Path(tmp) / "mosaic-12mp.jpg"]
        cv2.imwrite(str(photos[0]), data.coffee()[..., ::-1])
        cv2.imwrite(str(photos[1]), mosaic(4032, 3024)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 92])
        texture = str(Path(tmp) / "texture.png")
        cv2.imwrite(texture, data.astronaut()[::8, ::8, ::-1])
        for photo in photos:
            bench_callbacks(photo, texture, args.repeats)
        if args.browser:
            if not CHROMIUM.exists():
                raise SystemExit(f"--browser needs Chromium at {CHROMIUM}")
            for photo in photos:
                bench_browser(photo, args.repeats)


if __name__ == "__main__":
    main()
