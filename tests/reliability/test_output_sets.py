"""Output sets, write errors, API misuse and messages, in the test process (fast)."""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from skimage import data

import torchiid
from torchiid.cli import main
from torchiid.core.exceptions import ImageError, ParameterError, ShapeError, TorchiidError
from torchiid.eval import EvalOptions, EvalRunner
from torchiid.io import layer_file_names, load_image, write_layers
from torchiid.io.layers import OutputError, OutputSet, check_output_folder
from torchiid.params import Parameters

FAST = ["--iterations", "1", "--no-progress"]


def _photo(path, w=80, h=64):
    img = cv2.resize(data.chelsea(), (w, h), interpolation=cv2.INTER_AREA)[..., ::-1]
    assert cv2.imwrite(str(path), img)
    return path


def _layers():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(3, 64, 80, generator=g) * 0.8 + 0.1
    refl = (image / image.amax()).clamp(0, 1)
    shading = (image.sum(0, keepdim=True) / refl.sum(0, keepdim=True)).clamp_min(1e-3)
    return image, refl, shading


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ------------------------------------------------------------------------------------------
# OutputSet and write_layers


def test_an_interrupted_set_leaves_nothing_not_even_its_folder(tmp_path):
    out = tmp_path / "a" / "b"
    with pytest.raises(KeyboardInterrupt), OutputSet(out, label="x") as tx:
        tx.write("x-1.txt", lambda p: p.write_text("one"))
        assert out.is_dir() and len(_listing(out)) > 0  # a hidden folder holds the file
        raise KeyboardInterrupt
    assert _listing(tmp_path) == []


def test_a_set_is_committed_whole_and_respects_overwrite(tmp_path):
    (tmp_path / "x-1.txt").write_text("old")
    with OutputSet(tmp_path, overwrite=False, label="x") as tx:
        tx.write("x-1.txt", lambda p: p.write_text("new 1"))
        tx.write("x-2.txt", lambda p: p.write_text("new 2"))
        with pytest.raises(OutputError, match="x-1.txt exists; pass --overwrite"):
            tx.commit()
    assert _listing(tmp_path) == ["x-1.txt"] and (tmp_path / "x-1.txt").read_text() == "old"
    with OutputSet(tmp_path, label="x") as tx:
        tx.write("x-1.txt", lambda p: p.write_text("new 1"))
        tx.write("x-2.txt", lambda p: p.write_text("new 2"))
        assert tx.commit() == [tmp_path / "x-1.txt", tmp_path / "x-2.txt"]
    assert _listing(tmp_path) == ["x-1.txt", "x-2.txt"]
    assert (tmp_path / "x-1.txt").read_text() == "new 1"


def test_background_writes_keep_the_set_order_and_run_on_writer_threads(tmp_path):
    import threading

    threads = {}

    def slow(name, text, delay):
        def write(p):
            time.sleep(delay)  # the later files finish first
            threads[name] = threading.current_thread().name
            p.write_text(text)

        return write

    with OutputSet(tmp_path, label="x") as tx:
        tx.write("x-1.txt", slow("1", "one", 0.2), background=True)
        tx.write("x-2.txt", slow("2", "two", 0.0), background=True)
        tx.write("x-3.txt", lambda p: p.write_text("three"))  # on the calling thread
        assert tx.commit() == [tmp_path / f"x-{i}.txt" for i in (1, 2, 3)]
    assert [(tmp_path / f"x-{i}.txt").read_text() for i in (1, 2, 3)] == ["one", "two", "three"]
    assert all(t.startswith("torchiid-write") for t in threads.values())
    assert _listing(tmp_path) == ["x-1.txt", "x-2.txt", "x-3.txt"]


def test_a_failed_background_write_fails_the_commit_and_leaves_nothing(tmp_path):
    (tmp_path / "x-1.txt").write_text("old")

    def full(p):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OutputError, match=r"x-2.txt: cannot write \(No space left"):
        with OutputSet(tmp_path, label="x") as tx:
            tx.write("x-1.txt", lambda p: p.write_text("new"), background=True)
            tx.write("x-2.txt", full, background=True)
            tx.commit()
    assert _listing(tmp_path) == ["x-1.txt"] and (tmp_path / "x-1.txt").read_text() == "old"


def test_an_interrupt_lets_running_background_writes_finish_before_the_cleanup(tmp_path):
    started, finished = [], []

    def slow(p):
        started.append(p)
        time.sleep(0.3)
        p.write_text("late")  # the folder must still be there
        finished.append(p)

    with pytest.raises(KeyboardInterrupt), OutputSet(tmp_path / "out", label="x") as tx:
        tx.write("x-1.txt", slow, background=True)
        while not started:
            time.sleep(0.01)
        raise KeyboardInterrupt
    assert finished == started  # it completed (no error in the writer) before the removal
    assert _listing(tmp_path) == []


def test_a_failed_rename_puts_the_old_set_back(tmp_path, monkeypatch):
    image, refl, shading = _layers()
    write_layers(tmp_path, "p", image, refl, shading, shading_white=1.0, params_json="{}\n")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real_replace, calls = os.replace, []

    def flaky(src, dst):
        if Path(dst).parent == tmp_path or Path(dst).parent.name == "old":  # the commit's
            calls.append(dst)
            if len(calls) == 6:  # old 1-3 moved aside, new 1-2 placed: new 3 fails
                raise OSError(errno.EIO, "Input/output error", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr("torchiid.io.layers.os.replace", flaky)
    with pytest.raises(OutputError, match=r"p-reflectance.png: cannot write \(Input/output"):
        write_layers(tmp_path, "p", image * 0.5, refl, shading * 0.5, shading_white=1.0)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert _listing(tmp_path) == sorted(before)


def test_write_layers_without_overwrite_touches_nothing(tmp_path):
    image, refl, shading = _layers()
    (tmp_path / "p-preview.png").write_bytes(b"mine")
    with pytest.raises(OutputError, match="p-preview.png exists; pass --overwrite"):
        write_layers(tmp_path, "p", image, refl, shading, shading_white=1.0, overwrite=False)
    assert _listing(tmp_path) == ["p-preview.png"]
    assert (tmp_path / "p-preview.png").read_bytes() == b"mine"


def test_check_output_folder(tmp_path):
    (tmp_path / "file").write_text("x")
    check_output_folder(tmp_path)
    check_output_folder(tmp_path / "new" / "deeper")
    assert _listing(tmp_path) == ["file"]  # probes leave nothing, missing folders wait
    with pytest.raises(OutputError, match="output exists and is not a directory"):
        check_output_folder(tmp_path / "file")
    with pytest.raises(OutputError, match="file/sub: cannot create the output folder: .*file "):
        check_output_folder(tmp_path / "file" / "sub")
    (tmp_path / "link").symlink_to(tmp_path / "gone")
    with pytest.raises(OutputError, match="is a broken link"):
        check_output_folder(tmp_path / "link" / "sub")


# ------------------------------------------------------------------------------------------
# A write error in a batch: reported in one line, the batch goes on


def test_a_write_error_fails_one_image_and_the_batch_goes_on(tmp_path, monkeypatch, capsys):
    for name in ("a", "b", "c"):
        _photo(tmp_path / f"{name}.png")
    import torchiid.io.layers as layers

    real = layers.save_codes

    def disk_full_for_b(path, codes):  # on a writer thread
        if path.name == "b-preview.png":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, codes)

    monkeypatch.setattr(layers, "save_codes", disk_full_for_b)
    out = tmp_path / "out"
    argv = ["decompose", *(str(tmp_path / f"{n}.png") for n in "abc"), "-o", str(out), *FAST]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if line.startswith("torchiid: error:")]
    assert errors == [
        f"torchiid: error: {tmp_path / 'b.png'}: {out / 'b-preview.png'}: cannot write "
        "(No space left on device)"
    ]
    assert "torchiid: 1 of 3 input(s) failed" in err
    names = {p.name for p in out.iterdir()}
    made = {"manifest.jsonl", "a-sigma.exr", "c-sigma.exr"}
    assert names == set(layer_file_names("a")) | set(layer_file_names("c")) | made
    assert not [p for p in out.rglob(".*")]


def test_an_unexpected_error_is_one_line_and_the_batch_goes_on(tmp_path, monkeypatch, capsys):
    _photo(tmp_path / "a.png")
    _photo(tmp_path / "b.png")
    import torchiid.model as command

    real = command.decompose

    def buggy(image, *args, **kwargs):
        if image.shape[-1] == 80 and not hasattr(buggy, "done"):
            buggy.done = True
            raise TypeError("a bug")
        return real(image, *args, **kwargs)

    monkeypatch.setattr(command, "decompose", buggy)
    out = tmp_path / "out"
    assert main(["decompose", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(out)]
                + FAST) == 1  # fmt: skip
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert (
        f"torchiid: error: {tmp_path / 'a.png'}: internal error (TypeError: a bug); "
        "rerun with --verbose for the traceback"
    ) in err.splitlines()
    made = set(layer_file_names("b")) | {"b-sigma.exr", "manifest.jsonl"}
    assert {p.name for p in out.iterdir()} == made


# ------------------------------------------------------------------------------------------
# API misuse: torchiid's own errors, saying what to pass


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        (
            {"image": torch.empty(1, 3, 64, 64, device="meta")},
            ShapeError,
            "image is on the meta device .* pass a tensor that holds values",
        ),
        (
            {"image": torch.rand(1, 3, 64, 64), "mask": torch.ones(64, 64, device="meta")},
            ShapeError,
            "mask is on the meta device",
        ),
        (
            {"image": torch.rand(1, 3, 64, 64), "params": {"iterations": 1}},
            ParameterError,
            r"params must be a torchiid.Parameters, got dict; use Parameters.from_dict",
        ),
        (
            {"image": torch.rand(1, 3, 64, 64), "params": "paper"},
            ParameterError,
            r"got str; use Parameters\(\), Parameters.preset\(name\)",
        ),
        (
            {"image": np.zeros((64, 64, 3), np.float32)},
            ShapeError,
            r"expected image to be a torch.Tensor, got ndarray; pass linear RGB",
        ),
        ({"image": [[0.5]]}, ShapeError, "got list"),
        (
            {"image": torch.rand(1, 3, 64, 64), "mask": np.ones((64, 64), bool)},
            ShapeError,
            "expected mask to be a torch.Tensor .* got ndarray; use torch.as_tensor",
        ),
        (
            {"image": torch.rand(1, 3, 50, 80)},
            ImageError,
            r"image is 80x50 px; at least 60 px per side",
        ),
    ],
)
def test_api_misuse_raises_torchiid_errors(kwargs, error, match):
    kwargs = dict(kwargs)
    image = kwargs.pop("image")
    with pytest.raises(error, match=match):
        torchiid.decompose(image, **kwargs)


def test_the_module_checks_its_params_when_called():
    with pytest.raises(ParameterError, match="got dict"):
        torchiid.IntrinsicDecomposer({"iterations": 1})(torch.rand(1, 3, 64, 64))


def test_sizes_are_width_x_height_everywhere(tmp_path):
    small = _photo(tmp_path / "small.png", w=90, h=50)
    with pytest.raises(ImageError, match="is 90x50 px"):
        load_image(small)
    mask = np.full((40, 30), 255, np.uint8)
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    from torchiid.io import load_mask

    with pytest.raises(ImageError, match="mask is 30x40 px but the image is 80x64 px"):
        load_mask(tmp_path / "mask.png", shape=(64, 80))
    p = Parameters().replace(max_side=80)
    with pytest.raises(ParameterError, match=r"working resolution 80x16 \(--max-side 80\)"):
        torchiid.decompose(torch.rand(1, 3, 60, 300), p)


# ------------------------------------------------------------------------------------------
# Parameter files and the eval dataset path


@pytest.mark.parametrize(
    ("raw", "match"),
    [
        ('{"note": "café"}'.encode("latin-1"), r"not a UTF-8 text file \(byte 0xe9 at offset 13\)"),
        ('{"iterations": 2}'.encode("utf-16"), "not a UTF-8 text file"),
        (b'{"iterations": 2', "not a readable JSON file"),
        (b'{"lambda_l": Infinity}', "Infinity is not a valid value"),
        (b'{"lambda_l": 1e999}', "1e999 is out of range"),
        (b'{"lambda_l": 1' + b"0" * 400 + b"}", "invalid parameter value"),
        (b'{"iterationz": 2}', "Invalid parameter: iterationz"),
        (b"3", "got a JSON number"),
    ],
)
def test_bad_parameter_files_name_the_file(tmp_path, raw, match):
    path = tmp_path / "p.json"
    path.write_bytes(raw)
    with pytest.raises(ParameterError, match=match) as info:
        Parameters.from_json(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)


def test_a_utf8_parameter_file_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "p.json"
    path.write_bytes('\ufeff{"iterations": 2}'.encode())
    assert Parameters.from_json(path).iterations == 2


def test_eval_on_a_file_says_it_is_not_a_directory(tmp_path):
    f = _photo(tmp_path / "x.png")
    with pytest.raises(TorchiidError, match="x.png: is a file, not a mit dataset directory"):
        EvalRunner("mit", f, EvalOptions(method="r=i", output=tmp_path / "o"))
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------------------
# Decoder messages stay off the terminal


def test_libjpeg_damage_reports_reject_the_file_and_stay_off_stderr(tmp_path, capfd):
    rgb = cv2.resize(data.astronaut(), (80, 64))
    ok, buf = cv2.imencode(".jpg", rgb[..., ::-1])
    raw = buf.tobytes()
    sos = raw.index(b"\xff\xda")
    start = sos + 2 + int.from_bytes(raw[sos + 2 : sos + 4], "big")
    mid = start + (len(raw) - start) // 2
    path = tmp_path / "cut.jpg"  # a marker in the middle of the scan: libjpeg fills the rest
    path.write_bytes(raw[:mid] + b"\xff\xfe\x00\x02" + raw[mid:])
    with pytest.raises(ImageError, match="premature end of data segment"):
        load_image(path)
    assert capfd.readouterr().err == ""


def test_sigterm_cleans_up_like_ctrl_c(tmp_path, monkeypatch, capsys):
    import signal

    import torchiid.model as command

    _photo(tmp_path / "a.png")

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)  # the handler main() installed raises here
        raise AssertionError("SIGTERM did not interrupt")

    monkeypatch.setattr(command, "decompose", terminated)
    before = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "out"
    assert main(["decompose", str(tmp_path / "a.png"), "-o", str(out), *FAST]) == 130
    assert signal.getsignal(signal.SIGTERM) == before  # restored
    err = capsys.readouterr().err
    assert "Traceback" not in err and "torchiid: interrupted while processing" in err
    assert not out.exists()
