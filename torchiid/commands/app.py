"""``torchiid app``: serve the browser app (decompose and edit photos) on this machine.

The options are defined here without importing torch or Gradio; :func:`run` imports them.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys

__all__ = ["DESCRIPTION", "add_arguments", "gradio_installed", "run"]


def gradio_installed() -> bool:
    """Whether Gradio can be imported (without importing it)."""
    return importlib.util.find_spec("gradio") is not None


DESCRIPTION = (
    "Serve a page that decomposes photos (upload or drop a file), shows the reflectance and "
    "shading, edits them (light colour and intensity, shadows, an object's colour or albedo) "
    "and gives the layers and the edited photo to download. Needs pip install "
    "'torchiid[app]'. Ctrl-C stops the server."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``torchiid app`` (the run options come from the shared parent)."""
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: every "
        "network interface)",
    )
    p.add_argument(
        "--port", type=int, help="port to listen on (default: the first free one from 7860)"
    )
    p.add_argument(
        "--share",
        action="store_true",
        help="also make a public link through Gradio's share servers (off by default; "
        "photos then pass through them)",
    )
    p.add_argument(
        "--preset", default="default", help="the preset the page starts with (default: default)"
    )
    p.add_argument("--iterations", type=int, help="the alternations k the page starts with")
    p.add_argument(
        "--max-side",
        type=int,
        help="the working resolution the page starts with: longer side in px (0 = full "
        "resolution; default 512)",
    )


def run(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C or SIGTERM; returns the exit status (errors raise TorchiidError)."""
    from torchiid.core.device import resolve_device
    from torchiid.core.exceptions import ParameterError, TorchiidError
    from torchiid.core.memory import memory_limit

    if not gradio_installed():
        raise TorchiidError("torchiid app needs Gradio: pip install 'torchiid[app]'")
    import torchiid.app as app  # without Gradio yet: serve() imports it

    if args.iterations is not None and args.iterations < 1:
        raise ParameterError(f"--iterations must be >= 1, got {args.iterations}")
    if args.max_side is not None and args.max_side < 0:
        raise ParameterError(f"--max-side must be >= 0, got {args.max_side}")
    limit = None if args.memory_limit is None else memory_limit(args.memory_limit)
    config = app.AppConfig(
        preset=args.preset,
        iterations=args.iterations,
        max_side=args.max_side,
        device=str(resolve_device(args.device)),
        memory_limit=limit,
    )
    config.params()  # an unknown preset is a set-up error, before serving
    try:
        app.serve(config, host=args.host, port=args.port, share=args.share)
    except KeyboardInterrupt:
        print("torchiid app: stopped", file=sys.stderr)
    return 0
