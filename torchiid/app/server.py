"""Serving the page: a server with its own temporary folder, and a clean stop.

:class:`Server` builds the page and serves it on ``host:port`` with Gradio's queue, its
temporary files (Gradio's cache: uploads, the images it sends; the downloads) in a
:class:`~torchiid.app.files.ServerFolder` that closing it removes. :func:`serve` is what
``torchiid app`` runs: it makes that folder the process's temporary folder before Gradio is
imported (this module imports Gradio only when a server starts), prints the address and
serves until Ctrl-C (or SIGTERM), so nothing is left in temporary folders afterwards.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from torchiid.app.config import AppConfig
from torchiid.app.files import ServerFolder
from torchiid.core.exceptions import TorchiidError, one_line

__all__ = ["Server", "serve"]


class Server:
    """One running page.

    Args:
        config: what the page's decompositions use (:class:`~torchiid.app.AppConfig`).
        host: the address to listen on (``127.0.0.1``: this machine only).
        port: the port (``None``: the first free one from 7860).
        share: also open a public link through Gradio's share servers.
        folder: the server's temporary folder (default: a new one, activated while it
            serves and removed when it is closed).

    Example::

        with Server(AppConfig()) as server:
            print(server.url)  # http://127.0.0.1:7860/
    """

    def __init__(
        self,
        config: AppConfig,
        *,
        host: str = "127.0.0.1",
        port: int | None = None,
        share: bool = False,
        folder: ServerFolder | None = None,
    ) -> None:
        self.config = config
        self.host, self.port, self.share = host, port, share
        self.folder = folder
        self._own_folder = folder is None
        self.url: str | None = None
        self.share_url: str | None = None
        self._demo = None

    def start(self) -> str:
        """Start serving; returns the local address.

        Raises:
            TorchiidError: the server cannot listen there (the port is taken, ...).
        """
        if self.folder is None:
            self.folder = ServerFolder()
            self.folder.activate()
        try:
            from torchiid.app.ui import build_app, theme

            self._demo = build_app(self.config, self.folder)
            self._demo.queue(default_concurrency_limit=1)
            _, self.url, self.share_url = self._demo.launch(
                server_name=self.host,
                server_port=self.port,
                share=self.share,
                prevent_thread_lock=True,
                allowed_paths=[str(self.folder.sessions)],  # the downloads
                quiet=True,
                show_error=False,
                ssr_mode=False,
                mcp_server=False,
                pwa=False,
                theme=theme(),
            )
        except (OSError, ValueError) as exc:
            self.close()
            where = f"{self.host}:{self.port}" if self.port else self.host
            why = one_line(str(exc))
            if "Cannot find empty port" in why:  # Gradio's words for a port in use
                why = "the port is in use" if self.port else "no free port from 7860 to 7959"
                why += "; choose another with --port"
            raise TorchiidError(f"cannot serve on {where}: {why}") from None
        except BaseException:
            self.close()
            raise
        return self.url

    def close(self) -> None:
        """Stop serving and remove the server's temporary folder (may be called twice)."""
        if self._demo is not None:
            self._demo.close(verbose=False)
            self._demo = None
        if self._own_folder and self.folder is not None:
            self.folder.remove()
            self.folder = None

    def __enter__(self) -> Server:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def serve(
    config: AppConfig,
    *,
    host: str = "127.0.0.1",
    port: int | None = None,
    share: bool = False,
    out: TextIO | None = None,
) -> None:
    """Serve the page until Ctrl-C or SIGTERM (a ``KeyboardInterrupt``), then clean up.

    Args:
        config: what the page's decompositions use.
        host: the address to listen on.
        port: the port (``None``: the first free one from 7860).
        share: also open a public link through Gradio's share servers.
        out: where the address is printed (default: standard output).
    """
    out = out or sys.stdout
    folder = ServerFolder()
    folder.activate()  # before Gradio is imported: it keeps the folders it finds then
    try:
        with Server(config, host=host, port=port, share=share, folder=folder) as server:
            print(f"torchiid app: serving on {server.url} (Ctrl-C stops it)", file=out, flush=True)
            if server.share_url:
                print(f"torchiid app: public link {server.share_url}", file=out, flush=True)
            while True:
                time.sleep(3600)
    finally:
        folder.remove()
