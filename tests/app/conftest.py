"""The app's tests: small photos, bad files, and a ``torchiid app`` server in a subprocess.

Everything here skips cleanly without Gradio (the ``app`` extra); the browser tests also skip
without Debian's Chromium at ``/usr/bin/chromium`` (``.ci/run`` installs it: a browser cannot
be downloaded at run time).
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage import data

CHROMIUM = Path("/usr/bin/chromium")
#: Chromium in a closed network, as root, without a GPU
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
#: how long a server may take to start (torch and Gradio imports on a busy 2-core machine)
START_TIMEOUT = 180


def write_photo(path: Path, rgb: np.ndarray) -> Path:
    """Write an ``(h, w, 3)`` uint8 RGB array (PNG or JPEG by the suffix)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))
    return path


def header_only_png(path: Path, w: int, h: int) -> Path:
    """A PNG of a few bytes that declares ``w x h`` RGB pixels and holds none of them."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))
    return path


def coffee(w: int, h: int) -> np.ndarray:
    """skimage's coffee photo (600x400) resized to ``w x h``."""
    return cv2.resize(data.coffee(), (w, h), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="session")
def photos(tmp_path_factory):
    """Small photos and bad files: name -> path."""
    d = tmp_path_factory.mktemp("photos")
    chelsea = cv2.resize(data.chelsea(), (200, 150), interpolation=cv2.INTER_AREA)
    jpeg = write_photo(d / "cup.jpg", coffee(200, 134))
    raw = jpeg.read_bytes()
    (d / "truncated.jpg").write_bytes(raw[: len(raw) // 2])
    (d / "notes.txt").write_text("a shopping list, not a photo\n")
    return {
        "small": write_photo(d / "coffee.png", coffee(96, 64)),
        "chelsea": write_photo(d / "chelsea.png", chelsea),
        "coffee": write_photo(d / "coffee600.png", data.coffee()),
        "large": write_photo(d / "large.png", coffee(1500, 1000)),
        "huge": write_photo(d / "huge.jpg", coffee(3000, 2000)),
        "texture": write_photo(d / "texture.png", data.astronaut()[::16, ::16]),
        "jpeg": jpeg,
        "truncated": d / "truncated.jpg",
        "tiny": write_photo(d / "tiny.png", np.full((1, 1, 3), 200, np.uint8)),
        "text": d / "notes.txt",
        "declared": header_only_png(d / "declared.png", 30000, 20000),
        "panorama": write_photo(d / "panorama.png", coffee(1200, 80)),
    }


@pytest.fixture(scope="session")
def chelsea_session(photos):
    """The 200x150 chelsea photo opened in the app: 2 alternations (a plain function call)."""
    from torchiid.app.session import open_photo
    from torchiid.params import Parameters

    return open_photo(photos["chelsea"], Parameters().replace(iterations=2))


def free_port() -> int:
    """A port nothing listens on now (the OS's choice)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class AppProcess:
    """``torchiid app`` in a subprocess, with its own temporary folder (``TMPDIR``).

    Args:
        tmpdir: the subprocess's temporary folder.
        args: more options of ``torchiid app``.
    """

    def __init__(self, tmpdir: Path, *args: str) -> None:
        tmpdir.mkdir(parents=True, exist_ok=True)
        self.tmpdir = tmpdir
        env = {**os.environ, "TMPDIR": str(tmpdir), "PYTHONUNBUFFERED": "1"}
        port = free_port()
        cmd = [sys.executable, "-m", "torchiid.cli", "app", "--port", str(port), "--threads", "1"]
        self.proc = subprocess.Popen(
            [*cmd, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
            env=env,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self._readers = [
            threading.Thread(target=self._read, args=(stream, into), daemon=True)
            for stream, into in ((self.proc.stdout, self.stdout), (self.proc.stderr, self.stderr))
        ]
        for thread in self._readers:
            thread.start()
        self.url = self._wait_for_url()

    def _read(self, stream, into: list[str]) -> None:
        for line in stream:
            into.append(line)
            if into is self.stdout:
                self.lines.put(line)

    def _wait_for_url(self) -> str:
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.5)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            if "serving on " in line:
                return line.split("serving on ", 1)[1].split()[0]
        self.stop()
        raise RuntimeError(f"torchiid app did not start: {''.join(self.stderr)[-3000:]}")

    def stop(self, sig: int = signal.SIGINT) -> int:
        """Stop the server as Ctrl-C does; its exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for thread in self._readers:
            thread.join(timeout=10)
        for stream in (self.proc.stdout, self.proc.stderr):
            stream.close()
        return self.proc.returncode


@pytest.fixture
def start_app():
    """``start_app(tmpdir, *options)``: a ``torchiid app`` subprocess, stopped after the test."""
    started: list[AppProcess] = []

    def start(tmpdir: Path, *args: str) -> AppProcess:
        started.append(AppProcess(tmpdir, *args))
        return started[-1]

    yield start
    for server in started:
        server.stop()


@pytest.fixture(scope="session")
def browser_type_launch_args(browser_type_launch_args):
    """pytest-playwright's browser: Debian's Chromium, or the browser tests skip."""
    if not CHROMIUM.exists():
        pytest.skip(f"Chromium is not installed at {CHROMIUM} (Debian: apt-get install chromium)")
    return {**browser_type_launch_args, "executable_path": str(CHROMIUM), "args": CHROMIUM_ARGS}


@pytest.fixture(scope="session")
def browser_context_args(browser_context_args):
    """Pages as a laptop shows them, downloads allowed."""
    return {
        **browser_context_args,
        "viewport": {"width": 1280, "height": 1000},
        "accept_downloads": True,
    }


@pytest.fixture(scope="module")
def browser_app(photos, tmp_path_factory):
    """A server for the browser tests: 1 alternation, a memory limit that refuses "huge".

    The limit lies halfway between what the 600x400 coffee photo needs with 5 alternations
    (the screenshot's run) and what the 3000x2000 one needs with 1.
    """
    from torchiid.model import memory_needed
    from torchiid.params import Parameters

    flags = {"return_stage1": True, "return_iterations": True}
    fits = memory_needed(400, 600, Parameters().replace(iterations=5), **flags)
    refused = memory_needed(2000, 3000, Parameters().replace(iterations=1), **flags)
    limit = (fits + refused) / 2 / 1e9
    server = AppProcess(
        tmp_path_factory.mktemp("browser-app"), "--iterations", "1", "--memory-limit", f"{limit}"
    )
    yield server
    # SIGTERM (a closed session, a service manager) stops it as cleanly as Ctrl-C
    assert server.stop(signal.SIGTERM) == 0, "".join(server.stderr)[-2000:]
    assert list(server.tmpdir.iterdir()) == [], "temporary files were left behind"
