"""A process's set-up for a run (``torchiid.collection.worker``): a failure is no bad input."""

from __future__ import annotations

from torchiid.cli import main
from torchiid.collection import ImageJob, RunSettings, process_image
from torchiid.core.exceptions import ModelError
from torchiid.params import Parameters

from collection_helpers import FAST


def _run(*args):
    return main(["decompose", *map(str, args), *FAST])


def test_a_set_up_error_stops_the_run_and_is_never_a_bad_input(
    library, tmp_path, monkeypatch, capsys
):
    from torchiid.collection import worker

    def no_model(settings):
        raise ModelError("ONNX model not found at /nowhere/m.onnx; run `torchiid export-onnx`")

    monkeypatch.setattr(worker, "_STATES", {})
    monkeypatch.setattr(worker, "_new_state", no_model)
    out = tmp_path / "out"
    out.mkdir()  # an existing folder: a failure would be recorded at once
    cover = library / "cover.png"
    assert _run(cover, "-o", out) == 2
    assert capsys.readouterr().err.splitlines() == [
        "torchiid: error: cannot set up the run: ONNX model not found at /nowhere/m.onnx; "
        "run `torchiid export-onnx`"
    ]
    assert not (out / "manifest.jsonl").exists()
    # a Dask task: an "error" result (Dask retries it), never a bad input
    settings = RunSettings(out=out, params=Parameters(), method="retinex")
    result = process_image(ImageJob(0, str(cover), "cover"), settings)
    assert result.failure == "error" and result.status == "failed"
    assert result.message.startswith(f"{cover}: not processed: cannot set up the run: ONNX")
    monkeypatch.undo()
    assert _run(cover, "-o", out) == 0  # the model is back: it runs
    assert "1 done, 0 skipped, 0 failed" in capsys.readouterr().err
