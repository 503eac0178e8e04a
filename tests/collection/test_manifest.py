"""The run manifest: contents, skipping on a rerun, rehashing, retrying failures, the lock."""

from __future__ import annotations

import hashlib
import json
import os

import cv2
import numpy as np
import pytest

from torchiid.cli import main
from torchiid.collection import (
    Manifest,
    RunSettings,
    params_hash,
    plan,
    run_collection,
)
from torchiid.collection.job import ImageResult
from torchiid.collection.manifest import read_records, record_of
from torchiid.io.inputs import list_inputs, unique_keys
from torchiid.io.layers import layer_file_names
from torchiid.params import Parameters

from collection_helpers import FAST, photo


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
    why = f"decomposed from another version of {cover}, or from another file"
    assert f"cover-reflectance-linear16.png exists ({why}); pass --overwrite" in err
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
    assert "exists (written with other parameters); pass --overwrite" in capsys.readouterr().err
    assert _run(cover, "-o", out, "--save-npy", "--overwrite") == 0
    assert (out / "cover-reflectance.npy").is_file()
    assert len({r["params"] for r in _records(out)}) == 2


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
    why = "written with another mask"
    assert f"cover-reflectance-linear16.png exists ({why}); pass --overwrite" in (
        capsys.readouterr().err
    )


def test_the_skip_pass_is_linear_and_hashes_only_changed_files(tmp_path, monkeypatch, counting_os):
    import torchiid.collection.manifest as manifest

    n, folders = 120, ("", "a", "a/b")  # a third of the images in each output folder
    src, out = tmp_path / "src", tmp_path / "out"
    settings = RunSettings(out=out, params=Parameters(), method="retinex")
    phash = params_hash(settings)
    names = layer_file_names("x")
    keys = []
    for k, folder in enumerate(folders):
        (src / folder).mkdir(parents=True, exist_ok=True)
        (out / folder).mkdir(parents=True, exist_ok=True)
        keys += [f"{folder}/{i:05d}".lstrip("/") for i in range(k, n, len(folders))]
    with open(out / "manifest.jsonl", "w") as f:
        for i, key in enumerate(keys):
            path = src / f"{key}.png"
            path.write_bytes(i.to_bytes(4, "big"))
            st = path.stat()
            folder, _, stem = key.rpartition("/")
            files = [f"{folder}/{n}".lstrip("/").replace("x-", f"{stem}-", 1) for n in names]
            for name in files:
                (out / name).write_bytes(b"")
            result = ImageResult(i, key, str(path), "done", files=files)
            result.sha256, result.size, result.mtime_ns = _sha(path), st.st_size, st.st_mtime_ns
            f.write(json.dumps(record_of(result, phash)) + "\n")
    items = unique_keys(list_inputs([src], recursive=True))
    counting = counting_os("stat", "listdir")  # the calls of torchiid.collection.manifest
    monkeypatch.setattr(manifest, "os", counting)
    decided = plan(items, Manifest(out / "manifest.jsonl"), phash, out=out)
    assert len(decided.done_before) == n and not decided.todo and decided.hashed == 0
    # one stat per input and one listing per output folder, nothing per output file
    assert counting.calls == {"stat": n, "listdir": len(folders)}
    (out / "00006-preview.png").unlink()  # a missing output: that image runs again
    os.utime(src / "a" / "00007.png", ns=(0, 0))  # touched, same bytes: hashed, skipped
    decided = plan(items, Manifest(out / "manifest.jsonl"), phash, out=out)
    assert [j.key for j in decided.todo] == ["00006"] and decided.hashed == 1
    assert [r["key"] for r in decided.refreshed] == ["a/00007"]
