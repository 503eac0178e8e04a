"""The output folder's lock (``torchiid.collection.lock``): one run at a time."""

from __future__ import annotations

import os

from torchiid.cli import main
from torchiid.collection import OutputLock

from collection_helpers import FAST


def _run(*args):
    return main(["decompose", *map(str, args), *FAST])


def test_a_second_run_on_the_same_folder_is_refused(library, tmp_path, capsys):
    out = tmp_path / "out"
    with OutputLock(out) as lock:
        assert lock.held and (out / ".torchiid.lock").is_file()
        assert _run(library / "cover.png", "-o", out) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1
        assert "another torchiid run is writing into this folder (pid" in err[0]
        assert f"pid {os.getpid()} on" in err[0]
    assert not (out / ".torchiid.lock").exists() and not out.exists()  # created, removed
    out.mkdir()
    (out / ".torchiid.lock").write_text("left by a killed run: nobody holds it")
    assert _run(library / "cover.png", "-o", out) == 0
    assert not (out / ".torchiid.lock").exists()
