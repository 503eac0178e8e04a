"""``--workers N``: spawned worker processes, a killed worker's image retried, interrupts.

A worker is killed for real (SIGKILL from the test) while it holds an image whose files are
written but not yet in place: ``TORCHIID_TEST_HOLD=<stem>:<folder>`` makes the worker write its
pid into ``<folder>/<stem>.pid`` at that point and wait.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

from torchiid.cli import main
from torchiid.collection import RunSettings, SetupError, run_collection
from torchiid.collection.manifest import read_records
from torchiid.io.inputs import list_inputs
from torchiid.io.layers import layer_file_names
from torchiid.params import Parameters

from collection_helpers import (
    FAST,
    CompileCounter,
    decompose_compiling_a_kernel,
    decompose_counting_arenas,
    photo,
)


def _kill_when_held(folder, stem, sig=signal.SIGKILL, timeout=90):
    """A thread that kills the process that writes ``<folder>/<stem>.pid``."""
    marker = folder / f"{stem}.pid"

    def run():
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not marker.exists():
            time.sleep(0.05)
        if marker.exists():
            os.kill(int(marker.read_text()), sig)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


HELD_NOT_WRITTEN = re.compile(
    r"torchiid: interrupted while processing [^(]*IMG_0002\.png "
    r"\(nothing of (it|them) was written\)"
)


def _last(out):
    return {r["key"]: r for r in read_records(out / "manifest.jsonl")}


def test_a_killed_worker_loses_only_its_image_which_is_retried(
    library, tmp_path, monkeypatch, capsys
):
    hold = tmp_path / "hold"
    hold.mkdir()
    monkeypatch.setenv("TORCHIID_TEST_HOLD", f"IMG_0002:{hold}")
    out = tmp_path / "out"
    killer = _kill_when_held(hold, "IMG_0002")
    argv = ["decompose", str(library), "-r", "-o", str(out), "--workers", "2", *FAST]
    assert main(argv) == 1  # the bad file
    killer.join()
    err = capsys.readouterr().err
    assert "IMG_0002.png: its worker process died (killed by SIGKILL); trying it again" in err
    assert "4 done, 0 skipped, 1 failed" in err and "1 retried after their worker died" in err
    records = _last(out)
    assert records["2020/trip/IMG_0002"]["status"] == "done"
    assert records["2020/trip/IMG_0002"]["attempts"] == 2
    assert records["2020/broken"]["status"] == "failed"
    workers = {r["worker"] for r in records.values()}
    assert len(workers) >= 2 and str(os.getpid()) not in {w.split(":")[-1] for w in workers}
    made = {p.name for p in (out / "2020" / "trip").iterdir()}
    assert made == set(layer_file_names("IMG_0002"))  # complete, no temporary folder
    assert not list(out.rglob(".*"))


def test_an_image_whose_worker_dies_every_time_fails_alone(library, tmp_path, monkeypatch, capsys):
    hold = tmp_path / "hold"
    hold.mkdir()
    monkeypatch.setenv("TORCHIID_TEST_HOLD", f"cover:{hold}")
    out = tmp_path / "out"
    killer = _kill_when_held(hold, "cover")
    argv = ["decompose", str(library / "cover.png"), str(library / "2019"), "-o", str(out)]
    assert main([*argv, "--workers", "1", "--retries", "0", *FAST]) == 1
    killer.join()
    err = capsys.readouterr().err
    assert "cover.png: the worker process died while processing it (killed by SIGKILL)" in err
    records = _last(out)
    assert records["cover"]["failure"] == "worker" and records["IMG_0001"]["status"] == "done"
    assert not [p for p in out.iterdir() if p.name.startswith("cover")]
    assert not list(out.rglob(".*"))


def test_an_image_that_fails_with_its_worker_leaves_no_folder_made_for_it(
    library, tmp_path, monkeypatch, capsys
):
    hold = tmp_path / "hold"
    hold.mkdir()
    monkeypatch.setenv("TORCHIID_TEST_HOLD", f"IMG_0002:{hold}")
    out = tmp_path / "out"
    killer = _kill_when_held(hold, "IMG_0002")
    argv = ["decompose", str(library / "2020"), "-r", "-o", str(out), "--workers", "1"]
    assert main([*argv, "--retries", "0", *FAST]) == 1
    killer.join()
    err = capsys.readouterr().err
    assert "IMG_0002.png: the worker process died while processing it (killed by SIGKILL)" in err
    assert _last(out)["trip/IMG_0002"]["failure"] == "worker"
    assert not (out / "trip").exists()  # made for the image, empty once its files are gone
    assert (out / "IMG_0001-reflectance.png").is_file()


def _held_run(code: str, hold, *, own_group: bool) -> subprocess.Popen:
    """Run Python ``code`` with ``IMG_0002`` held; returns once the hold has begun."""
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONUNBUFFERED": "1",
        "TORCHIID_TEST_HOLD": f"IMG_0002:{hold}",
    }
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=own_group,  # its own process group, like a terminal's foreground job
    )
    marker = hold / "IMG_0002.pid"
    deadline = time.monotonic() + 90
    while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert marker.exists(), proc.communicate()[1]
    return proc


def _main_code(args: list[str], *before: str) -> str:
    """Python code that runs the ``torchiid`` console script on ``args`` after ``before``."""
    lines = ["import signal, sys", *before, "from torchiid.cli import console_main"]
    return "\n".join([*lines, f"sys.argv = ['torchiid', *{args!r}]", "console_main()", ""])


def test_ctrl_c_stops_every_worker_and_leaves_no_partial_outputs(library, tmp_path):
    hold = tmp_path / "hold"
    hold.mkdir()
    out = tmp_path / "out"
    args = ["decompose", str(library), "-r", "-o", str(out), "--workers", "2", *FAST]
    proc = _held_run(_main_code(args), hold, own_group=True)
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the whole group
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, err
    assert "Traceback" not in err, err
    assert HELD_NOT_WRITTEN.search(err), err
    made = [str(p.relative_to(out)) for p in out.rglob("*")]
    assert not (out / "2020" / "trip").exists(), (made, err)  # nothing of the held image
    assert not list(out.rglob(".*"))  # no temporary folder, no lock
    for record in read_records(out / "manifest.jsonl"):
        assert record["key"] != "2020/trip/IMG_0002"
        for name in record["files"]:
            assert (out / name).is_file()


def test_a_worker_killed_before_it_can_stop_leaves_nothing_of_its_image(library, tmp_path):
    # The run is interrupted (SIGINT to the parent alone) and the worker on the held image gets
    # no time to stop (STOP_GRACE 0): it is killed before it removes what it wrote, so the
    # parent removes the image's temporary files and the folders made for it.
    hold = tmp_path / "hold"
    hold.mkdir()
    out = tmp_path / "out"
    args = ["decompose", str(library / "2020"), "-r", "-o", str(out), "--workers", "1", *FAST]
    no_grace = ["import torchiid.collection.pool as pool", "pool.STOP_GRACE = 0.0"]
    proc = _held_run(_main_code(args, *no_grace), hold, own_group=False)
    assert list((out / "trip").glob(".torchiid-IMG_0002-*"))  # written, not yet in place
    os.kill(proc.pid, signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, err
    assert HELD_NOT_WRITTEN.search(err), err
    assert not (out / "trip").exists(), err  # nothing of the held image
    assert (out / "IMG_0001-reflectance.png").is_file()  # the image done before it stays
    assert not list(out.rglob(".*"))


def test_a_run_that_ignores_sigint_keeps_its_workers_going_through_one(library, tmp_path):
    # As a job a shell starts in the background: SIGINT is ignored from the start, so a SIGINT
    # to the whole group stops nothing; the held image then completes in its first worker.
    hold = tmp_path / "hold"
    hold.mkdir()
    out = tmp_path / "out"
    args = ["decompose", str(library), "-r", "-o", str(out), "--workers", "2", *FAST]
    ignore = "signal.signal(signal.SIGINT, signal.SIG_IGN)"
    proc = _held_run(_main_code(args, ignore), hold, own_group=True)
    os.killpg(proc.pid, signal.SIGINT)
    time.sleep(1.0)  # time for a worker that took it to stop
    (hold / "IMG_0002.go").touch()
    err = proc.communicate(timeout=90)[1]
    assert proc.returncode == 1, err  # the bad file
    assert "4 done, 0 skipped, 1 failed" in err and "retried" not in err, err
    assert _last(out)["2020/trip/IMG_0002"]["attempts"] == 1


def test_sigterm_to_one_worker_is_a_worker_death_not_the_end_of_the_run(
    library, tmp_path, monkeypatch, capsys
):
    hold = tmp_path / "hold"
    hold.mkdir()
    monkeypatch.setenv("TORCHIID_TEST_HOLD", f"cover:{hold}")
    out = tmp_path / "out"
    killer = _kill_when_held(hold, "cover", sig=signal.SIGTERM)
    argv = ["decompose", str(library / "cover.png"), str(library / "2019"), "-o", str(out)]
    assert main([*argv, "--workers", "1", *FAST]) == 0
    killer.join()
    err = capsys.readouterr().err
    assert "cover.png: its worker process died (stopped by SIGTERM); trying it again" in err
    assert "2 done, 0 skipped, 0 failed" in err
    records = _last(out)
    assert records["cover"]["status"] == "done" and records["cover"]["attempts"] == 2
    assert not list(out.rglob(".*"))


def test_a_worker_that_cannot_be_set_up_stops_the_run(library, tmp_path):
    out = tmp_path / "out"
    settings = RunSettings(
        out=out, params=Parameters(), method="retinex", mask=tmp_path / "gone.png"
    )
    items = list_inputs([library / "cover.png"])
    with pytest.raises(SetupError, match=r"a worker process cannot set up the run: .*gone.png"):
        run_collection(items, settings, workers=1)
    assert not out.exists()  # nothing recorded: no image failed


def test_a_script_without_a_main_guard_is_told_why_its_workers_die(library, tmp_path):
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from pathlib import Path\n"
        "from torchiid.collection import RunSettings, run_collection\n"
        "from torchiid.io.inputs import list_inputs\n"
        "from torchiid.params import Parameters\n"
        f"items = list_inputs([{str(library / 'cover.png')!r}])\n"
        f"settings = RunSettings(out=Path({str(tmp_path / 'out')!r}), params=Parameters(),"
        " method='retinex')\n"
        "run_collection(items, settings, workers=1)\n"
    )
    run = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert run.returncode == 1
    last = run.stderr.strip().splitlines()[-1]
    assert "the worker processes die before they take an image" in last
    assert 'if __name__ == "__main__":' in last


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_a_worker_s_threads_share_one_malloc_arena(tmp_path, monkeypatch):
    count = tmp_path / "arenas.txt"
    monkeypatch.setenv("TORCHIID_TEST_ARENAS", str(count))  # the worker inherits it
    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    src = photo(tmp_path / "in" / "a.png")
    settings = RunSettings(out=tmp_path / "out", params=Parameters().replace(iterations=1))
    items = list_inputs([src])
    summary = run_collection(items, settings, workers=1, decompose_fn=decompose_counting_arenas)
    assert summary.done == 1
    assert count.read_text().count("Arena ") == 1  # glibc's default: one more per thread


def test_workers_compiling_the_kernels_are_said_once(tmp_path):
    sources = [photo(tmp_path / "in" / f"{n}.png", seed=i) for i, n in enumerate("ab")]
    settings = RunSettings(out=tmp_path / "out", params=Parameters().replace(iterations=1))
    told = CompileCounter()
    summary = run_collection(
        list_inputs(sources),
        settings,
        workers=2,
        decompose_fn=decompose_compiling_a_kernel,
        reporter=told,
    )
    assert summary.done == 2
    assert told.compiled == 1  # each worker compiles; the run says it once


@pytest.mark.parametrize(("on", "them"), [(["a.png"], "it"), (["a.png", "b.png"], "them")])
def test_the_interrupt_line_names_the_images_it_stopped(
    library, tmp_path, monkeypatch, capsys, on, them
):
    import torchiid.collection
    from torchiid.collection import RunInterrupted, RunSummary

    def interrupted(*args, **kwargs):
        raise RunInterrupted(RunSummary(total=5, done=2, interrupted_on=on))

    monkeypatch.setattr(torchiid.collection, "run_collection", interrupted)
    argv = ["decompose", str(library / "cover.png"), "-o", str(tmp_path / "out"), *FAST]
    assert main(argv) == 130
    names = ", ".join(on)
    line = f"torchiid: interrupted while processing {names} (nothing of {them} was written);"
    assert f"{line} 2 of 5 input(s) written" in capsys.readouterr().err
