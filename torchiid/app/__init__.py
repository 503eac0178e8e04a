"""``torchiid app``: decompose and edit photos in the browser (Gradio).

The page is a thin layer over the library: :func:`torchiid.decompose` with its progress
callback, the edits of :mod:`torchiid.edit` on the layers kept at the preview resolution,
and :func:`torchiid.io.write_layers` for the downloads. Modules: :mod:`~torchiid.app.config`
(what a server uses), :mod:`~torchiid.app.session` (one photo and its layers),
:mod:`~torchiid.app.objects` (click-to-select), :mod:`~torchiid.app.edits` (the edits
composed), :mod:`~torchiid.app.files` (downloads and the server's temporary folder),
:mod:`~torchiid.app.callbacks` (the page's callbacks as plain functions),
:mod:`~torchiid.app.ui` (the page, :func:`~torchiid.app.ui.build_app`) and
:mod:`~torchiid.app.server` (serving it).

Only this package imports Gradio (``pip install 'torchiid[app]'``), and only when a server
starts or its ``callbacks`` and ``ui`` modules are imported; ``import torchiid`` does not.
"""

import torchiid.app.offline  # noqa: F401 - first: before anything imports Gradio
from torchiid.app.config import AppConfig
from torchiid.app.server import Server, serve

__all__ = ["AppConfig", "Server", "serve"]
