"""``torchiid app`` on a port that is taken: a one-line error, and nothing left behind."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest

pytest.importorskip("gradio")


def test_a_taken_port_is_a_one_line_error_and_leaves_nothing(tmp_path):
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cmd = [sys.executable, "-m", "torchiid.cli", "app", "--port", str(port)]
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert done.stderr == (
        f"torchiid: error: cannot serve on 127.0.0.1:{port}: the port is in use; choose another "
        "with --port\n"
    )
    assert done.stdout == ""
    assert list(tmp_path.iterdir()) == []  # the server's temporary folder is gone
