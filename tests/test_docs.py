"""The documentation site: it builds strictly, its API pages cover the public names, and the
user guide's code that rebuilds a photo from the output files runs against real files."""

from __future__ import annotations

import importlib
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage import data

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

#: the packages and public modules whose ``__all__`` the API reference must cover
PUBLIC = (
    "torchiid",
    "torchiid.baselines",
    "torchiid.collection",
    "torchiid.core",
    "torchiid.edit",
    "torchiid.eval",
    "torchiid.features",
    "torchiid.io",
    "torchiid.losses",
    "torchiid.model",
    "torchiid.params",
    "torchiid.priors",
    "torchiid.resample",
    "torchiid.solvers",
    "torchiid.stages",
    "torchiid.synthetic",
    "torchiid.video",
)


def test_site_builds_strictly(tmp_path):
    """A broken link, a missing page or an API name that no longer exists fails the build."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert (tmp_path / "api" / "model" / "index.html").is_file()
    assert (tmp_path / "benchmarks" / "index.html").is_file()
    parameters = (tmp_path / "reference" / "parameters" / "index.html").read_text()
    assert "base_mix" in parameters and "converged" in parameters


def _resolve(path: str) -> object:
    """The object a ``::: dotted.path`` directive documents."""
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        return obj
    raise ModuleNotFoundError(path)


def test_api_pages_cover_every_public_name():
    directives = [
        m.group(1)
        for page in sorted((DOCS / "api").glob("*.md"))
        for m in re.finditer(r"^::: ([\w.]+)", page.read_text(), re.M)
    ]
    documented = [_resolve(path) for path in directives]
    missing = []
    for module_name in PUBLIC:
        module = importlib.import_module(module_name)
        for name in module.__all__:
            obj = getattr(module, name)
            if not any(obj is d for d in documented):
                missing.append(f"{module_name}.{name}")
    assert not missing, f"not on the API pages (docs/api/*.md): {missing}"


def _code_after(page: Path, heading: str) -> str:
    """The first Python block of ``page`` after the text ``heading``."""
    text = page.read_text()
    return _code_after_text(text[text.index(heading) :])


def test_rebuild_snippet_runs_on_the_files_decompose_writes(tmp_path, monkeypatch):
    from torchiid.cli import main

    code = _code_after(DOCS / "guide" / "outputs.md", "### Rebuild the input from the files")
    photo = cv2.resize(data.coffee(), (180, 120), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "photo.png"), photo[..., ::-1])
    monkeypatch.chdir(tmp_path)
    argv = ["decompose", "photo.png", "-o", "out/", "--iterations", "1", "--no-progress"]
    assert main(argv) == 0
    rebuilt: dict = {"__name__": "snippet"}
    exec(compile(code, "docs/guide/outputs.md", "exec"), rebuilt)
    # the next block reads the EXR without torchiid: the same shading and view factor
    code = _code_after(DOCS / "guide" / "outputs.md", "Without torchiid, the EXR opens")
    plain: dict = {"__name__": "snippet"}
    exec(compile(code, "docs/guide/outputs.md", "exec"), plain)
    np.testing.assert_array_equal(plain["S"], rebuilt["S"])
    np.testing.assert_allclose(np.ravel(plain["white"])[0], rebuilt["white"], rtol=1e-6)


def _code_after_text(text: str) -> str:
    """The first Python block of ``text``."""
    match = re.search(r"```python\n(.*?)```", text, re.S)
    assert match, "no Python block in the text"
    return match.group(1)


@pytest.mark.parametrize("name", ["README.md", "docs/index.md"])
def test_front_pages_show_committed_pictures_under_the_size_limit(name):
    text = (ROOT / name).read_text()
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+\.jpg)\)", text)
    assert pictures, f"{name} shows no picture"
    base = ROOT if name == "README.md" else DOCS
    for picture in pictures:
        path = base / picture
        assert path.is_file(), f"{name}: {picture} does not exist"
        assert path.stat().st_size <= 250 * 1024, f"{picture} is over 250 KB"


def test_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250
    text = "\n".join(lines)
    # the two set-up commands that .ci/run runs
    assert "pip install torch==2.13.0 && pip install -e '.[test]'" in text
    assert "python -m pytest -q -n 2" in text
    ci = (ROOT / ".ci" / "run").read_text()
    assert "pip install torch==2.13.0 && pip install -e '.[test]'" in ci
    assert "python -m pytest -q -n 2" in ci
