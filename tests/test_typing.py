"""The mathematics layer type-checks strictly: mypy with the configuration in pyproject.toml."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_mypy_reports_no_error_on_the_configured_packages():
    """``torchiid/core``, ``torchiid/priors`` and ``torchiid/solvers`` in strict mode."""
    run = subprocess.run(
        [sys.executable, "-m", "mypy", "--no-color-output", "--no-error-summary"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert "No module named mypy" not in run.stderr, "mypy is missing: pip install -e '.[test]'"
    assert run.returncode == 0, run.stdout + run.stderr
