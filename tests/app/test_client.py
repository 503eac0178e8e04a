"""The served app through ``gradio_client``: the decompose endpoint, errors, a clean stop."""

from __future__ import annotations

import signal
import zipfile

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("gradio")

from gradio_client import Client, handle_file  # noqa: E402
from gradio_client.exceptions import AppError  # noqa: E402

from torchiid.app.files import layer_names  # noqa: E402


def test_the_decompose_endpoint_then_a_stop_that_leaves_no_temporary_file(
    photos, tmp_path, start_app
):
    server = start_app(tmp_path / "tmp", "--iterations", "1")
    try:
        client = Client(server.url, verbose=False, download_files=str(tmp_path / "downloads"))
        endpoints = client.view_api(print_info=False, return_format="dict")["named_endpoints"]
        decompose = next(name for name in endpoints if "decompose" in name)
        params = endpoints[decompose]["parameters"]
        assert params[0]["component"] == "File"  # the photo comes first
        returns = [(r["label"], r["component"]) for r in endpoints[decompose]["returns"]]
        assert returns[1:] == [
            ("Reflectance", "Image"),
            ("Shading", "Image"),
            ("Run info", "Markdown"),
        ]
        assert returns[0][0].startswith("Photo")  # every output has a name, none "value_N"

        photo, refl, shading, info = client.predict(
            handle_file(str(photos["chelsea"])), "default", 1, 512, api_name=decompose
        )
        views = []
        for path in (photo, refl, shading):
            with Image.open(path) as image:
                views.append(np.asarray(image.convert("RGB")))
        for view in views:
            assert view.shape == (150, 200, 3)
        assert np.abs(views[1].astype(int) - views[0].astype(int)).mean() > 5
        assert (views[2][..., 0] == views[2][..., 1]).all()  # a gray shading
        assert "**chelsea.png**: 200×150 px" in info

        # the layers of the same session, as the zip the page offers
        zip_path = client.predict(api_name="/layers")
        with zipfile.ZipFile(zip_path) as zf:
            assert zf.namelist() == layer_names("chelsea")

        with pytest.raises(AppError) as err:
            client.predict(handle_file(str(photos["text"])), "default", 1, 512, api_name=decompose)
        message = str(err.value)
        assert "notes.txt: is not an image" in message and str(server.tmpdir) not in message
        client.close()
    finally:
        status = server.stop(signal.SIGINT)
    assert status == 0
    err = "".join(server.stderr)
    assert "torchiid app: stopped" in err and "Traceback" not in err
    assert list(server.tmpdir.iterdir()) == []
