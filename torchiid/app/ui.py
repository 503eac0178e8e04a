"""The page: Gradio components and the events that tie them to the callbacks.

Layout: the photo's file and the run's settings on the left; the photo, reflectance and
shading side by side, and a before/after slider, on the right; the edits and the downloads
below; every alternation's layers and the run's report in folds at the bottom.

Events: uploading a photo (or the Decompose button, the API endpoint ``/decompose``)
decomposes it in Gradio's queue, one decomposition at a time, with the model's progress
callback driving the progress bar; then the gallery, the preview and the layers' zip follow.
Each edit control reruns only :meth:`~torchiid.app.callbacks.Callbacks.preview` on the
layers kept in the tab's state (the last move wins when moves come faster than previews).
"""

from __future__ import annotations

import gradio as gr

from torchiid.app.callbacks import CLEARED, COMPARE, EDIT_FIELDS, Callbacks, forget
from torchiid.app.config import AppConfig
from torchiid.app.edits import EditSettings
from torchiid.app.files import ServerFolder
from torchiid.params import PRESETS

__all__ = ["build_app", "theme"]

INTRO = """# torchiid: reflectance and shading
Open a photo to split it into its **reflectance** (the colours of things) and its
**shading** (the light on them), `photo = reflectance × shading`; then relight or recolour it
and take the layers away. Everything runs on this machine."""

#: Gradio's temporary files older than 2 hours are removed every 30 minutes
DELETE_CACHE = (1800, 7200)

_PRIVATE = {"api_visibility": "private"}
_HEAVY = {"concurrency_id": "decompose", "concurrency_limit": 1}
#: every preview listener: one at a time, in the order the controls moved, so a preview
#: started before the last move never lands after it and shows edits the controls no longer
#: have (Gradio's queue is first in, first out within a concurrency group)
_EDIT = {
    "concurrency_id": "edit",
    "concurrency_limit": 1,
    "trigger_mode": "always_last",
    "show_progress": "hidden",
    **_PRIVATE,
}


def theme() -> gr.themes.Base:
    """Gradio's default theme with the system's fonts: the page loads nothing from outside."""
    return gr.themes.Default(
        font=["ui-sans-serif", "system-ui", "sans-serif"],
        font_mono=["ui-monospace", "monospace"],
    )


def _layer_image(label: str, elem_id: str) -> gr.Image:
    """One of the three images side by side: the photo, its reflectance, its shading."""
    return gr.Image(label=label, interactive=False, format="png", height=230, elem_id=elem_id)


def _edit_controls() -> dict[str, gr.components.Component]:
    """The edit controls, one per field of :class:`~torchiid.app.edits.EditSettings`."""
    d = EditSettings()
    c: dict[str, gr.components.Component] = {}
    with gr.Column(min_width=240):
        gr.Markdown("### Edit the light")
        c["merge"] = gr.Checkbox(
            d.merge, label="Edit the merged layers of both stages", elem_id="merge"
        )
        c["tint"] = gr.ColorPicker(d.tint, label="Light colour", elem_id="tint")
        c["tint_strength"] = gr.Slider(
            0, 1, d.tint_strength, step=0.05, label="Light colour strength", elem_id="tint-strength"
        )
        c["intensity"] = gr.Slider(
            0, 1, d.intensity, step=0.05, label="Light in indirectly lit areas", elem_id="intensity"
        )
        c["soften"] = gr.Slider(
            -1, 1, d.soften, step=0.05, label="Soften shadows (below 0: deepen)", elem_id="soften"
        )
    with gr.Column(min_width=240):
        gr.Markdown("### Edit the selected object")
        c["hue"] = gr.Slider(-180, 180, d.hue, step=5, label="Hue (degrees)", elem_id="hue")
        c["chroma"] = gr.Slider(0, 2, d.chroma, step=0.05, label="Chroma", elem_id="chroma")
        c["flatten"] = gr.Checkbox(d.flatten, label="Flatten its texture", elem_id="flatten")
        c["texture"] = gr.File(
            label="New albedo (an image) for it", type="filepath", height=100, elem_id="texture"
        )
        c["fit"] = gr.Radio(["tile", "stretch"], value=d.fit, label="Albedo fit", elem_id="fit")
        c["scale"] = gr.Slider(0.1, 4, d.scale, step=0.1, label="Albedo tile size", elem_id="scale")
    assert tuple(c) == EDIT_FIELDS  # the order the callbacks read the values in
    return c


def build_app(config: AppConfig, folder: ServerFolder) -> gr.Blocks:
    """The page of a server with this configuration and temporary folder."""
    calls = Callbacks(config, folder)
    params = config.params()
    with gr.Blocks(title="torchiid", analytics_enabled=False, delete_cache=DELETE_CACHE) as demo:
        gr.Markdown(INTRO)
        session = gr.State(None, delete_callback=forget)
        selection = gr.State(None)
        with gr.Row():
            with gr.Column(scale=1, min_width=280):
                gr.Markdown("### Open a photo")
                photo_file = gr.File(
                    label="Photo: PNG, JPEG, TIFF, WebP, BMP, OpenEXR or .npy",
                    type="filepath",
                    height=140,
                    elem_id="photo-file",
                )
                preset = gr.Dropdown(
                    list(PRESETS), value=config.preset, label="Preset", elem_id="preset"
                )
                iterations = gr.Slider(
                    1, 10, params.iterations, step=1, label="Alternations k", elem_id="iterations"
                )
                max_side = gr.Slider(
                    0,
                    2048,
                    params.output.max_side,
                    step=32,
                    label="Working resolution: longer side in px (0: the photo's own)",
                    elem_id="max-side",
                )
                run = gr.Button("Decompose", variant="primary", elem_id="decompose")
                gr.Markdown("### Take it away")
                layers_file = gr.File(
                    label="Layers (.zip: the files of torchiid decompose)",
                    interactive=False,
                    height=90,
                    elem_id="layers-zip",
                )
                render_full = gr.Button(
                    "Edited photo at full resolution", variant="primary", elem_id="render-full"
                )
                edited_file = gr.File(
                    label="Edited photo (PNG)", interactive=False, height=90, elem_id="edited-file"
                )
            with gr.Column(scale=3):
                with gr.Row():
                    photo = _layer_image("Photo: click an object to select it", "photo")
                    reflectance = _layer_image("Reflectance", "reflectance")
                    shading = _layer_image("Shading", "shading")
                compare_view = gr.ImageSlider(
                    label="Before / after",
                    format="jpeg",  # sent at every slider move: encoded in 1 ms, PNG in 100
                    interactive=False,
                    max_height=460,
                    elem_id="compare",
                )
                compare = gr.Radio(
                    list(COMPARE), value=COMPARE[0], label="Compare with", elem_id="compare-with"
                )
        with gr.Row():
            controls = _edit_controls()
            with gr.Column(min_width=240):
                gr.Markdown("### Selection")
                status = gr.Markdown(
                    "Open a photo, then click an object in it.", elem_id="selection-status"
                )
                size = gr.Slider(
                    0, 1, 0, step=1, label="Selection size (larger objects under the click)",
                    elem_id="selection-size",
                )  # fmt: skip
                clear = gr.Button("Clear the selection", elem_id="clear-selection")
                reset = gr.Button("Reset the edits", elem_id="reset-edits")
        with gr.Accordion("Every alternation's layers", open=False):
            gallery = gr.Gallery(columns=4, format="png", elem_id="iterations-gallery")
        with gr.Accordion("Run info", open=True):
            info = gr.Markdown(label="Run info", elem_id="info")  # its name in the API

        values = list(controls.values())
        preview_in = [session, selection, compare, *values]
        decompose_in = [photo_file, preset, iterations, max_side, session]
        decompose_out = [session, photo, reflectance, shading, info]
        clicked = run.click(
            calls.decompose, decompose_in, decompose_out, api_name="decompose", **_HEAVY
        )
        uploaded = photo_file.upload(
            calls.decompose, decompose_in, decompose_out, **_PRIVATE, **_HEAVY
        )
        outputs = {
            "session": session,
            "photo": photo,
            "reflectance": reflectance,
            "shading": shading,
            "info": info,
            "compare_view": compare_view,
            "layers_file": layers_file,
            "edited_file": edited_file,
            "gallery": gallery,
            "selection": selection,
            "size": size,
            "status": status,
        }
        cleared = [outputs[name] for name in CLEARED]
        for event, api in ((clicked, {"api_name": "layers"}), (uploaded, _PRIVATE)):
            event.failure(calls.failed, [session, photo_file], cleared, **_PRIVATE)
            event.success(
                calls.details, [session], [gallery, selection, size, status], **_PRIVATE
            ).success(calls.preview, preview_in, [compare_view], **_EDIT).success(
                calls.layers_zip, [session], [layers_file], **api, **_HEAVY
            )
        for name, control in controls.items():
            if name == "texture":  # a file that cannot be read is removed, not kept failing
                checked = control.change(
                    calls.check_albedo, [session, control], [control], **_PRIVATE
                )
                checked.success(calls.preview, preview_in, [compare_view], **_EDIT)
            elif isinstance(control, gr.ColorPicker):  # a typed #rrggbb fires no input event
                control.change(calls.preview, preview_in, [compare_view], **_EDIT)
            else:
                control.input(calls.preview, preview_in, [compare_view], **_EDIT)
        compare.input(calls.preview, preview_in, [compare_view], **_EDIT)
        photo.select(calls.select, [session], [selection, photo, size, status], **_PRIVATE).success(
            calls.preview, preview_in, [compare_view], **_EDIT
        )
        size.input(
            calls.resize_selection,
            [session, selection, size],
            [selection, photo, status],
            trigger_mode="always_last",
            **_PRIVATE,
        ).success(calls.preview, preview_in, [compare_view], **_EDIT)
        clear.click(
            calls.clear_selection, [session], [selection, photo, size, status], **_PRIVATE
        ).then(calls.preview, preview_in, [compare_view], **_EDIT)
        defaults = EditSettings()
        reset.click(
            lambda: [getattr(defaults, name) for name in EDIT_FIELDS], None, values, **_PRIVATE
        ).then(calls.preview, preview_in, [compare_view], **_EDIT)
        render_full.click(
            calls.full_resolution, [session, selection, *values], [edited_file], **_PRIVATE,
            **_HEAVY,
        )  # fmt: skip
    return demo
