"""``torchiid.openmp``: the shorter OpenMP spin-wait is set before torch is imported."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = (
    "import os, torchiid, torchiid.openmp as o; print(o.TOO_LATE, os.environ.get('GOMP_SPINCOUNT'))"
)


def _probe(code: str, **env: str) -> str:
    base = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    proc = subprocess.run(
        [sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


@pytest.mark.parametrize(
    ("env", "want"), [({}, "False 30000"), ({"GOMP_SPINCOUNT": "7"}, "False 7")]
)
def test_set_before_torch_unless_the_user_set_it(env, want):
    # nothing that `import torchiid` runs imports torch before the setting is made
    assert _probe(PROBE, **env) == want


def test_torch_imported_first_is_reported():
    assert _probe("import torch; " + PROBE) == "True 30000"
