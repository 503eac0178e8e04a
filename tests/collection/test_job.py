"""One image of a collection (``torchiid.collection.job``): its outcome, never a crash."""

from __future__ import annotations

import pytest

from torchiid.cli import main
from torchiid.collection import ImageJob, Manifest, RunSettings, run_collection
from torchiid.collection.manifest import read_records
from torchiid.features import patches
from torchiid.io.inputs import list_inputs
from torchiid.model import decompose
from torchiid.params import Parameters

from collection_helpers import FAST, photo


def _last(out):
    return {r["key"]: r for r in read_records(out / "manifest.jsonl")}


def _run(*args):
    return main(["decompose", *map(str, args), *FAST])


def test_complete_files_without_a_record_are_recognised(library, tmp_path, capsys):
    out = tmp_path / "out"
    cover = library / "cover.png"
    assert _run(cover, "-o", out) == 0
    before = (out / "cover-shading.exr").stat().st_mtime_ns
    (out / "manifest.jsonl").unlink()  # as if the run had stopped before recording it
    assert _run(cover, "-o", out, "--no-progress") == 0
    assert _last(out)["cover"]["status"] == "done"
    assert (out / "cover-shading.exr").stat().st_mtime_ns == before  # not recomputed
    with open(out / "manifest.jsonl", "a") as f:
        f.write('{"key": "cov')  # a torn last line of a killed run
    assert len(Manifest(out / "manifest.jsonl")) == 1
    assert _run(cover, "-o", out) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().err
    other = library / "2019" / "IMG_0001.png"
    assert _run(cover, other, "-o", out) == 0  # its record goes after the torn line
    assert "1 done, 1 skipped" in capsys.readouterr().err
    manifest = Manifest(out / "manifest.jsonl")
    assert sorted(manifest.records) == ["IMG_0001", "cover"] and manifest.bad_lines == 1


def _interrupted_in_a_kernel(*args, **kwargs):
    """What Ctrl-C inside a numba kernel raises: SystemError caused by the KeyboardInterrupt."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as exc:
        raise SystemError("CPUDispatcher(...) returned a result with an exception set") from exc


def test_ctrl_c_inside_a_compiled_kernel_is_an_interruption_not_a_failed_image(tmp_path):
    from torchiid.collection.job import process_image

    path = photo(tmp_path / "a.png")
    settings = RunSettings(out=tmp_path / "out", params=Parameters(), method="semantic")
    job = ImageJob(0, str(path), "a")
    with pytest.raises(KeyboardInterrupt):
        process_image(job, settings, decompose_fn=_interrupted_in_a_kernel)
    out = tmp_path / "out"
    assert not out.exists() or not any(out.iterdir())


def _plain_bug(*args, **kwargs):
    raise SystemError("a real internal error")


def test_a_system_error_without_an_interrupt_still_fails_the_image(tmp_path):
    from torchiid.collection.job import process_image

    path = photo(tmp_path / "a.png")
    settings = RunSettings(out=tmp_path / "out", params=Parameters(), method="semantic")
    result = process_image(ImageJob(0, str(path), "a"), settings, decompose_fn=_plain_bug)
    assert result.status == "failed" and result.failure == "error"


def test_solver_note_tells_a_breakdown_from_a_cap():
    from torchiid.collection.job import solver_note
    from torchiid.model import SolveReport

    ok = SolveReport("shading", 1, 12, 0, 5e-5, 1e-4, 3000, True)
    capped = SolveReport("reflectance", 1, 400, 2000, 2e-4, 5e-5, 400, False)
    broke = SolveReport("shading", 5, 20, 0, 1.3e-3, 1e-4, 3000, False)
    assert solver_note("a.png", [ok], True, "a-info.json") == (None, None)
    note, detail = solver_note("a.png", [ok, capped], False, "a-info.json")
    assert note is None and "the preset's caps" in detail and "a-info.json" in detail
    note, detail = solver_note("a.png", [ok, capped], True, "a-info.json")
    assert detail is None and "raise cg_max_iter" in note
    note, _ = solver_note("a.png", [capped, broke], True, "a-info.json")
    assert "no further progress" in note and "--verbose" in note and "2 of 2" in note


def test_a_manifest_that_cannot_be_written_stops_the_run_before_any_image(
    library, tmp_path, capsys
):
    out = tmp_path / "out"
    (out / "manifest.jsonl").mkdir(parents=True)  # there, and no file can be added to
    argv = ["decompose", str(library / "cover.png"), "-o", str(out), *FAST]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "manifest.jsonl: cannot be written" in err and "records every image there" in err
    assert sorted(p.name for p in out.iterdir()) == ["manifest.jsonl"]  # nothing written


def test_a_run_whose_images_all_fail_gives_no_rate(library, tmp_path, capsys):
    argv = ["decompose", str(library / "2020" / "broken.png"), "-o", str(tmp_path / "o"), *FAST]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "0 done, 0 skipped, 1 failed" in err and "images/minute" not in err


@pytest.mark.parametrize("release", [True, False])
def test_a_run_here_gives_back_the_cnn_after_the_last_image_s_features(
    tmp_path, monkeypatch, release
):
    events: list[str] = []
    monkeypatch.setattr(patches, "release_feature_extractors", lambda: events.append("released"))

    def spying(image, params, *, progress, **kwargs):
        def spy(stage, k, total):
            events.append(stage)
            progress(stage, k, total)

        return decompose(image, params, progress=spy, **kwargs)

    srcs = [photo(tmp_path / "in" / f"{n}.png", n) for n in range(2)]
    settings = RunSettings(out=tmp_path / "out", params=Parameters().replace(iterations=1))
    summary = run_collection(
        list_inputs(srcs), settings, decompose_fn=spying, release_models=release
    )
    assert summary.done == 2
    # the second image's features are the last the run needs: released before its solves
    last = ["features", "released", "iteration"] if release else ["features", "iteration"]
    assert events == ["features", "iteration", *last]
