"""The run manifest: contents, skipping on a rerun, rehashing, retrying failures, the lock."""

from __future__ import annotations

import hashlib
import json
import os
import time

import cv2
import numpy as np
import pytest

from torchiid.cli import main
from torchiid.collection import (
    Manifest,
    OutputLock,
    RunSettings,
    params_hash,
    plan,
    run_collection,
)
from torchiid.collection.job import ImageJob, ImageResult
from torchiid.collection.manifest import read_records, record_of
from torchiid.core.exceptions import ModelError
from torchiid.io.inputs import list_inputs, unique_keys
from torchiid.io.layers import layer_file_names
from torchiid.params import Parameters

from conftest import FAST, photo


def _records(out):
    return list(read_records(out / "manifest.jsonl"))


def _last(out):
    return {r["key"]: r for r in _records(out)}


def _run(*args):
    return main(["decompose", *map(str, args), *FAST])


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_manifest_records_every_image(library, tmp_path, capsys):
    out = tmp_path / "out"
    assert _run(library, "-r", "-o", out) == 1
    err = capsys.readouterr().err
    assert "torchiid: 4 done, 0 skipped, 1 failed" in err
    assert "torchiid: 1 of 5 input(s) failed" in err
    records = _last(out)
    assert sorted(records) == [
        "2019/IMG_0001",
        "2020/IMG_0001",
        "2020/broken",
        "2020/trip/IMG_0002",
        "cover",
    ]
    done = records["2020/trip/IMG_0002"]
    src = library / "2020" / "trip" / "IMG_0002.png"
    settings = RunSettings(out=out, params=Parameters(), method="retinex")
    assert done["status"] == "done" and done["message"] is None and done["failure"] is None
    assert done["input"] == str(src) and done["sha256"] == _sha(src)
    assert done["size"] == src.stat().st_size and done["mtime_ns"] == src.stat().st_mtime_ns
    assert done["params"] == params_hash(settings) and done["attempts"] == 1
    assert done["files"] == [f"2020/trip/{n}" for n in layer_file_names("IMG_0002")]
    assert all((out / f).is_file() for f in done["files"]) and done["seconds"] > 0
    info = json.loads((out / "2020/trip/IMG_0002-info.json").read_text())
    assert info["input_sha256"] == done["sha256"] and info["params_hash"] == done["params"]
    bad = records["2020/broken"]
    assert bad["status"] == "failed" and bad["files"] == [] and bad["failure"] == "input"
    assert "broken.png: is not an image" in bad["message"] and "\n" not in bad["message"]
    # the two IMG_0001 of different folders keep their folders: no collision
    a = cv2.imread(str(out / "2019" / "IMG_0001-reflectance.png"))
    b = cv2.imread(str(out / "2020" / "IMG_0001-reflectance.png"))
    assert a is not None and b is not None and not np.array_equal(a, b)
    assert not list(out.rglob(".*"))  # no lock, no temporary folder left


def test_a_rerun_skips_what_is_done_and_what_failed(library, tmp_path, capsys):
    out = tmp_path / "out"
    assert _run(library, "-r", "-o", out) == 1
    lines = len(_records(out))
    stamp = {p: p.stat().st_mtime_ns for p in out.rglob("*.png")}
    capsys.readouterr()
    assert _run(library, "-r", "-o", out) == 1  # the bad file still fails
    err = capsys.readouterr().err
    assert "torchiid: 0 done, 5 skipped (1 failed before), 0 failed" in err
    assert "broken.png: failed before" in err and "--retry-failed" in err
    assert len(_records(out)) == lines  # nothing appended
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.png")} == stamp
    # --retry-failed tries it again (and it fails again)
    assert _run(library, "-r", "-o", out, "--retry-failed") == 1
    assert "0 done, 4 skipped, 1 failed" in capsys.readouterr().err
    assert len(_records(out)) == lines + 1
    # once repaired, the changed file is no longer "failed before": it runs without the flag
    photo(library / "2020" / "broken.png", 5)
    assert _run(library, "-r", "-o", out) == 0
    assert "1 done, 4 skipped, 0 failed" in capsys.readouterr().err
    assert _last(out)["2020/broken"]["status"] == "done"


def test_a_changed_input_is_hashed_again(library, tmp_path, capsys):
    out = tmp_path / "out"
    items = unique_keys(list_inputs([library / "cover.png", library / "2019"]))
    settings = RunSettings(out=out, params=Parameters(), method="retinex")
    first = run_collection(items, settings)
    assert (first.done, first.skipped_done) == (2, 0)
    cover = library / "cover.png"
    os.utime(cover, ns=(cover.stat().st_atime_ns, cover.stat().st_mtime_ns + 10**9))
    again = run_collection(items, settings)  # touched, same bytes: hashed, still skipped
    assert (again.done, again.skipped_done, again.hashed) == (0, 2, 1)
    refreshed = _last(out)["cover"]  # a record with the new time was appended
    assert refreshed["mtime_ns"] == cover.stat().st_mtime_ns and refreshed["status"] == "done"
    third = run_collection(items, settings)  # so the next rerun need not hash it again
    assert third.hashed == 0 and third.skipped_done == 2
    photo(cover, 7)  # new content: run again, but its old files are not replaced silently
    capsys.readouterr()
    assert _run(cover, library / "2019", "-o", out) == 1
    err = capsys.readouterr().err
    assert "cover-reflectance-linear16.png exists; pass --overwrite" in err
    assert _last(out)["cover"]["failure"] == "output"
    assert _run(cover, library / "2019", "-o", out, "--overwrite") == 0  # output failures rerun
    assert "1 done, 1 skipped, 0 failed" in capsys.readouterr().err
    assert _last(out)["cover"]["sha256"] == _sha(cover)
    info = json.loads((out / "cover-info.json").read_text())
    assert info["input_sha256"] == _sha(cover)


def test_other_parameters_are_not_skipped(library, tmp_path, capsys):
    out = tmp_path / "out"
    cover = library / "cover.png"
    assert _run(cover, "-o", out) == 0
    assert _run(cover, "-o", out, "--save-npy") == 1  # another parameters hash
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert _run(cover, "-o", out, "--save-npy", "--overwrite") == 0
    assert (out / "cover-reflectance.npy").is_file()
    assert len({r["params"] for r in _records(out)}) == 2


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


def test_a_set_up_error_stops_the_run_and_is_never_a_bad_input(
    library, tmp_path, monkeypatch, capsys
):
    from torchiid.collection import job

    def no_model(settings):
        raise ModelError("ONNX model not found at /nowhere/m.onnx; run `torchiid export-onnx`")

    monkeypatch.setattr(job, "_STATES", {})
    monkeypatch.setattr(job, "_new_state", no_model)
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
    result = job.process_image(ImageJob(0, str(cover), "cover"), settings)
    assert result.failure == "error" and result.status == "failed"
    assert result.message.startswith(f"{cover}: not processed: cannot set up the run: ONNX")
    monkeypatch.undo()
    assert _run(cover, "-o", out) == 0  # the model is back: it runs
    assert "1 done, 0 skipped, 0 failed" in capsys.readouterr().err


@pytest.mark.parametrize(
    "failure, skipped", [("input", True), ("error", False), ("worker", False), ("output", False)]
)
def test_only_bad_inputs_are_skipped_as_failed_before(library, tmp_path, failure, skipped):
    out = tmp_path / "out"
    out.mkdir()
    cover = library / "cover.png"
    st = cover.stat()
    phash = params_hash(RunSettings(out=out, params=Parameters(), method="retinex"))
    result = ImageResult(0, "cover", str(cover), "failed", "why", failure=failure)
    result.sha256, result.size, result.mtime_ns = _sha(cover), st.st_size, st.st_mtime_ns
    (out / "manifest.jsonl").write_text(json.dumps(record_of(result, phash)) + "\n")
    items = unique_keys(list_inputs([cover]))
    decided = plan(items, Manifest(out / "manifest.jsonl"), phash, out=out)
    assert (len(decided.failed_before), len(decided.todo)) == ((1, 0) if skipped else (0, 1))
    decided = plan(items, Manifest(out / "manifest.jsonl"), phash, out=out, retry_failed=True)
    assert len(decided.todo) == 1


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


def test_list_file_masks_and_a_failure_into_an_existing_folder(library, tmp_path, capsys):
    mask = np.zeros((64, 80), np.uint8)
    mask[16:48, 20:60] = 255
    cv2.imwrite(str(library / "mask.png"), mask)
    listing = library / "selection.csv"
    listing.write_text(
        "path,mask\ncover.png,mask.png\n2019/IMG_0001.png,\nmissing.png,\n"
        "2020/broken.png,mask.png\n"
    )
    out = tmp_path / "out"
    out.mkdir()
    argv = ["decompose", "--list", str(listing), "-o", str(out), *FAST]
    assert main(argv) == 1
    refl = cv2.imread(str(out / "cover-reflectance.png"))
    assert (refl[:16] == 0).all() and refl[30, 40].any()  # the row's own mask
    records = _last(out)
    assert records["cover"]["mask"] == str(library / "mask.png")
    assert records["cover"]["mask_sha256"] == _sha(library / "mask.png")
    assert records["missing"]["message"].endswith("missing.png: no such file")
    assert records["2019/IMG_0001"]["status"] == "done"
    broken = records["2020/broken"]
    assert broken["failure"] == "input" and broken["mask_sha256"] == _sha(library / "mask.png")
    capsys.readouterr()
    assert main(argv) == 1  # the bad image with its own mask is skipped too
    assert "0 done, 4 skipped (2 failed before), 0 failed" in capsys.readouterr().err
    (out / "manifest.jsonl").unlink()  # complete files without a record: their mask counts
    assert main(argv) == 1
    assert "2 done, 0 skipped, 2 failed" in capsys.readouterr().err
    assert _last(out)["cover"]["mask_sha256"] == _sha(library / "mask.png")
    assert json.loads((out / "cover-info.json").read_text())["mask_sha256"] == _sha(
        library / "mask.png"
    )
    assert main(argv) == 1
    assert "0 done, 4 skipped (2 failed before), 0 failed" in capsys.readouterr().err
    mask[16:48, 10:70] = 255  # another mask: the files there are not this decomposition
    cv2.imwrite(str(library / "mask.png"), mask)
    assert main(argv) == 1
    assert "cover-reflectance-linear16.png exists; pass --overwrite" in capsys.readouterr().err


def test_the_skip_pass_is_linear_and_hashes_only_changed_files(tmp_path):
    n = 3000
    src, out = tmp_path / "src", tmp_path / "out"
    src.mkdir()
    out.mkdir()
    settings = RunSettings(out=out, params=Parameters(), method="retinex")
    phash = params_hash(settings)
    names = layer_file_names("x")
    with open(out / "manifest.jsonl", "w") as f:
        for i in range(n):
            path = src / f"{i:05d}.png"
            path.write_bytes(i.to_bytes(4, "big"))
            st = path.stat()
            files = [n.replace("x-", f"{i:05d}-", 1) for n in names]
            for name in files:
                (out / name).write_bytes(b"")
            result = ImageResult(i, f"{i:05d}", str(path), "done", files=files)
            result.sha256, result.size, result.mtime_ns = _sha(path), st.st_size, st.st_mtime_ns
            f.write(json.dumps(record_of(result, phash)) + "\n")
    items = unique_keys(list_inputs([src]))
    t0 = time.perf_counter()
    decided = plan(items, Manifest(out / "manifest.jsonl"), phash, out=out)
    seconds = time.perf_counter() - t0
    assert len(decided.done_before) == n and not decided.todo and decided.hashed == 0
    assert seconds < 3, seconds
    (out / "00007-preview.png").unlink()  # a missing output: that image runs again
    os.utime(src / "00009.png", ns=(0, 0))
    decided = plan(items, Manifest(out / "manifest.jsonl"), phash, out=out)
    assert [j.key for j in decided.todo] == ["00007"] and decided.hashed == 1


def test_no_inputs_and_conflicting_options_are_usage_errors(tmp_path, capsys):
    assert main(["decompose", "-o", str(tmp_path / "o")]) == 2
    assert (
        "no inputs: name image files, folders or globs, or --list FILE" in capsys.readouterr().err
    )
    cover = photo(tmp_path / "c.png")
    argv = ["decompose", str(cover), "-o", str(tmp_path / "o")]
    assert main([*argv, "--workers", "2", "--dask-scheduler", "tcp://x:1"]) == 2
    assert "--workers and --dask-scheduler exclude each other" in capsys.readouterr().err
    assert main([*argv, "--workers", "0"]) == 2
    assert "--workers must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:9"])
def test_an_unreachable_scheduler_is_a_set_up_error(tmp_path, capsys, monkeypatch, address):
    monkeypatch.setattr("torchiid.collection.dask_runner.CONNECT_TIMEOUT", 1.0)
    cover = photo(tmp_path / "c.png")
    argv = ["decompose", str(cover), "-o", str(tmp_path / "o"), "--dask-scheduler", address]
    assert main([*argv, *FAST]) == 2
    err = capsys.readouterr().err
    assert f"cannot reach the Dask scheduler at {address}" in err
    assert not (tmp_path / "o").exists()


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


def test_the_parameters_hash_does_not_depend_on_the_version(monkeypatch, tmp_path):
    # a new version that computes the same files keeps a collection's records
    import torchiid
    from torchiid.collection.job import RunSettings, params_hash

    settings = RunSettings(out=tmp_path, params=Parameters.preset("converged"))
    before = params_hash(settings)
    monkeypatch.setattr(torchiid, "__version__", "99.0.0")
    assert json.loads(settings.params.to_json())["torchiid_version"] == "99.0.0"
    assert params_hash(settings) == before
    assert params_hash(RunSettings(out=tmp_path, params=Parameters())) != before
