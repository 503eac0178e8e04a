"""``--dask-scheduler``: a real local cluster (2 worker processes), a bad file, a killed worker.

One worker process is killed (SIGKILL, from the test) while it holds an image whose files are
written but not in place (``TORCHIID_TEST_HOLD``, see ``torchiid.collection.job``); the
scheduler re-runs that task on a worker, every good image ends ``done``, the bad file
``failed``, and no partial or temporary file is left.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from torchiid.cli import main
from torchiid.collection import RunInterrupted, RunSettings, run_collection
from torchiid.collection.manifest import read_records
from torchiid.io.inputs import InputItem
from torchiid.io.layers import layer_file_names
from torchiid.params import Parameters

from collection_helpers import FAST, CompileCounter, decompose_compiling_a_kernel, photo

distributed = pytest.importorskip("distributed")


@pytest.fixture
def cluster(monkeypatch, tmp_path):
    hold = tmp_path / "hold"
    hold.mkdir()
    # the worker processes inherit the environment: the hook and one thread each
    monkeypatch.setenv("TORCHIID_TEST_HOLD", f"IMG_0002:{hold}")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=50,
    ) as c:
        yield c, hold


def test_a_dask_cluster_run_survives_a_killed_worker(library, tmp_path, cluster, capsys):
    c, hold = cluster
    marker = hold / "IMG_0002.pid"
    killed = []

    def kill_when_held():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not marker.exists():
            time.sleep(0.05)
        if marker.exists():
            pid = int(marker.read_text())
            killed.append(pid)
            os.kill(pid, signal.SIGKILL)

    killer = threading.Thread(target=kill_when_held, daemon=True)
    killer.start()
    out = tmp_path / "out"
    argv = ["decompose", str(library), "-r", "-o", str(out), "--retries", "1"]
    assert main([*argv, "--dask-scheduler", c.scheduler_address, *FAST]) == 1  # the bad file
    killer.join()
    assert killed, "the held image never reached a worker"
    err = capsys.readouterr().err
    assert "4 done, 0 skipped, 1 failed" in err and "broken.png: is not an image" in err
    records = {r["key"]: r for r in read_records(out / "manifest.jsonl")}
    assert {k: r["status"] for k, r in records.items()} == {
        "cover": "done",
        "2019/IMG_0001": "done",
        "2020/IMG_0001": "done",
        "2020/broken": "failed",
        "2020/trip/IMG_0002": "done",
    }
    assert records["2020/broken"]["failure"] == "input"
    held = records["2020/trip/IMG_0002"]
    assert str(killed[0]) != held["worker"].split(":")[-1]  # done by another worker process
    workers = {r["worker"].split(":")[-1] for r in records.values()}
    assert str(os.getpid()) not in workers  # the workers wrote the files, not the client
    for record in records.values():
        assert all((out / name).is_file() for name in record["files"])
    made = {p.name for p in (out / "2020" / "trip").iterdir()}
    assert made == set(layer_file_names("IMG_0002"))
    assert not list(out.rglob(".*"))  # no temporary folder of the killed worker, no lock
    # a rerun through the cluster skips everything
    assert main([*argv, "--dask-scheduler", c.scheduler_address, *FAST]) == 1
    assert "0 done, 5 skipped (1 failed before), 0 failed" in capsys.readouterr().err


def test_workers_compiling_the_kernels_are_said_once_on_the_client(tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    sources = [photo(tmp_path / "in" / f"{n}.png", seed=i) for i, n in enumerate("abc")]
    settings = RunSettings(out=tmp_path / "out", params=Parameters().replace(iterations=1))
    told = CompileCounter()
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=50
    ) as c:
        summary = run_collection(
            [InputItem(path=p, key=p.stem) for p in sources],
            settings,
            scheduler=c.scheduler_address,
            decompose_fn=decompose_compiling_a_kernel,
            reporter=told,
        )
    assert summary.done == 3
    assert told.compiled == 1  # every task compiles (uncached); the run says it once


def _buggy_decompose(*args, **kwargs):
    raise RuntimeError("out of luck")


def test_a_dask_task_raises_only_what_a_retry_may_cure(library, tmp_path):
    from torchiid.collection import ImageJob, RunSettings, params_hash
    from torchiid.collection.dask_runner import ImageTaskError, dask_task
    from torchiid.params import Parameters

    settings = RunSettings(out=tmp_path / "out", params=Parameters(), method="semantic")
    phash = params_hash(settings)
    bad = ImageJob(0, str(library / "2020" / "broken.png"), "broken")
    result = dask_task(bad, settings, phash, _buggy_decompose)  # a bad input: a result
    assert result.status == "failed" and result.failure == "input"
    good = ImageJob(1, str(library / "cover.png"), "cover")
    with pytest.raises(ImageTaskError, match=r"cover.png: RuntimeError: out of luck"):
        dask_task(good, settings, phash, _buggy_decompose)  # Dask retries it (retries=)
    assert not (tmp_path / "out").exists()


def _interrupt_when_held(marker, go=None):
    """Ctrl-C (SIGINT to this process) once the held task runs; then maybe release it."""

    def run():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not marker.exists():
            time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGINT)
        if go is not None:
            time.sleep(0.3)
            go.touch()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_ctrl_c_waits_for_the_running_tasks_and_names_those_left(
    library, tmp_path, cluster, monkeypatch, capsys, caplog
):
    c, hold = cluster
    marker, go = hold / "IMG_0002.pid", hold / "IMG_0002.go"
    src = library / "2020" / "trip" / "IMG_0002.png"
    out = tmp_path / "out"
    settings = RunSettings(out=out, params=Parameters(), method="retinex")
    # the task ends within the wait: it is recorded
    waiter = _interrupt_when_held(marker, go)
    with pytest.raises(RunInterrupted) as stop:
        run_collection([InputItem(src, "IMG_0002")], settings, scheduler=c.scheduler_address)
    waiter.join()
    assert (stop.value.summary.done, stop.value.summary.left_running) == (1, [])
    records = list(read_records(out / "manifest.jsonl"))
    assert [r["status"] for r in records] == ["done"]
    assert all((out / name).is_file() for name in records[0]["files"])
    # a task still running after the wait is named: it may still write its files
    monkeypatch.setattr("torchiid.collection.dask_runner.STOP_GRACE", 0.5)
    marker.unlink()
    go.unlink()
    out2 = tmp_path / "out2"
    waiter = _interrupt_when_held(marker)
    argv = ["decompose", str(src), "-o", str(out2), "--dask-scheduler", c.scheduler_address]
    assert main([*argv, *FAST]) == 130
    waiter.join()
    os.kill(int(marker.read_text()), signal.SIGKILL)  # the task would go on for a minute
    err = capsys.readouterr().err
    assert "waiting up to 0.5 s for the 1 image(s) running on the cluster" in caplog.text
    assert "note: 1 image(s) were still running on the cluster and may still write" in err
    assert str(src) in err.splitlines()[-1]


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:9"])
def test_an_unreachable_scheduler_is_a_set_up_error(tmp_path, capsys, monkeypatch, address):
    monkeypatch.setattr("torchiid.collection.dask_runner.CONNECT_TIMEOUT", 1.0)
    cover = photo(tmp_path / "c.png")
    argv = ["decompose", str(cover), "-o", str(tmp_path / "o"), "--dask-scheduler", address]
    assert main([*argv, *FAST]) == 2
    err = capsys.readouterr().err
    assert f"cannot reach the Dask scheduler at {address}" in err
    assert not (tmp_path / "o").exists()
