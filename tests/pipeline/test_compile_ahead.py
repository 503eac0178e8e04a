"""Stage 2's kernels compiled in a second process during a first run (compile_ahead)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from torchiid.params import Parameters
from torchiid.params.presets import PRESETS, VARIANTS
from torchiid.pipeline import compile_ahead
from torchiid.pipeline.compile_ahead import (
    ENVIRONMENT_VARIABLE,
    CompileAhead,
    compiling_ahead,
)

#: the kernels only Stage 2 calls, which the helper exists to compile
STAGE2_KERNELS = {"_bregman_update", "_add_halos", "_affinity_exponent", "_scale_by_factor"}

SLEEPER = [sys.executable, "-c", "import time; time.sleep(60)"]


def test_the_helper_gets_the_run_s_threads_and_parameters(monkeypatch):
    monkeypatch.delenv(ENVIRONMENT_VARIABLE, raising=False)
    paper = Parameters.preset("paper")
    cmd = CompileAhead(paper, threads=3).command()
    assert cmd[:3] == [sys.executable, "-m", "torchiid.pipeline.compile_ahead"]
    assert cmd[cmd.index("--threads") + 1] == "3"
    assert cmd[cmd.index("--parent") + 1] == str(os.getpid())  # it ends with this run
    assert Parameters.from_dict(json.loads(cmd[cmd.index("--params") + 1])) == paper
    # the parameters may come from a function, asked when the helper starts
    asked = []
    later = CompileAhead(lambda: asked.append(1) or None, threads=2)
    assert asked == []
    assert "--params" not in later.command() and asked == [1]


def test_no_helper_for_parameters_that_never_run_stage2(monkeypatch):
    monkeypatch.delenv(ENVIRONMENT_VARIABLE, raising=False)
    assert CompileAhead(Parameters().variant("baseline1"), threads=2).command() is None
    assert CompileAhead(Parameters().variant("baseline2"), threads=2).command() is not None


@pytest.mark.parametrize("name", [*PRESETS, *VARIANTS])
def test_the_helper_runs_stage2_of_every_preset_and_variant(name, monkeypatch):
    import torch

    monkeypatch.setattr(os, "nice", lambda increment: 0)  # not this test process's priority
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)  # nor its threads
    watched = []
    monkeypatch.setattr(compile_ahead, "_exit_with", watched.append)
    p = Parameters.preset(name) if name in PRESETS else Parameters().variant(name)
    p = p.replace(iterations=2)
    argv = ["--threads", "1", "--params", json.dumps(p.to_dict()), "--parent", "12345"]
    assert compile_ahead.main(argv) == 0
    assert watched == [12345]  # it ends with the run that started it


def test_no_helper_on_one_thread_or_when_switched_off(monkeypatch):
    monkeypatch.delenv(ENVIRONMENT_VARIABLE, raising=False)
    one = CompileAhead(threads=1)
    assert one.command() is None
    assert one.start() is False and one.process is None
    monkeypatch.setenv(ENVIRONMENT_VARIABLE, "0")
    off = CompileAhead(threads=2)
    assert off.command() is None and off.start() is False and off.process is None
    monkeypatch.setenv(ENVIRONMENT_VARIABLE, "1")
    assert CompileAhead(threads=2).command() is not None


def test_started_once_and_stopped_when_the_run_ends(monkeypatch):
    monkeypatch.setattr(CompileAhead, "command", lambda self: SLEEPER)
    with compiling_ahead(threads=2) as ahead:
        assert ahead.start() is True
        first = ahead.process
        assert ahead.start() is True and ahead.process is first  # one helper per run
        assert first.poll() is None  # still running while the run goes on
    assert first.wait(timeout=10) == -signal.SIGTERM  # stopped by the end of the block
    ahead.close()  # closing again does nothing


def test_a_helper_that_ends_is_reaped_while_the_run_goes_on(monkeypatch):
    monkeypatch.setattr(CompileAhead, "command", lambda self: [sys.executable, "-c", "pass"])
    with compiling_ahead(threads=2) as ahead:
        assert ahead.start() is True
        deadline = time.monotonic() + 30
        while ahead.process.returncode is None and time.monotonic() < deadline:
            time.sleep(0.05)  # no poll() here: the helper's own waiting thread reaps it
        assert ahead.process.returncode == 0  # no zombie left for a long-running app


def test_nothing_starts_after_the_run_has_ended(monkeypatch):
    monkeypatch.setattr(CompileAhead, "command", lambda self: SLEEPER)
    with compiling_ahead(threads=2) as ahead:
        pass
    assert ahead.start() is False and ahead.process is None  # a compilation after close


def test_the_helper_exits_when_its_run_is_gone(tmp_path):
    # a run killed outright: the helper's parent ends without stopping it
    code = textwrap.dedent(
        """
        import os, subprocess, sys
        child = subprocess.Popen([sys.executable, "-c",
            "from torchiid.pipeline import compile_ahead as c; import sys, time; "
            f"c._exit_with({os.getpid()}); time.sleep(60)"], stdout=subprocess.DEVNULL)
        print(child.pid, flush=True)
        """
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    pid = int(run.stdout.split()[0])
    deadline = time.monotonic() + 20
    while _running(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    if _running(pid):
        os.kill(pid, signal.SIGKILL)
        pytest.fail("the helper outlived the run that started it")


def _running(pid: int) -> bool:
    """Whether process ``pid`` runs (an exited one that nobody has reaped yet does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rpartition(")")[2].split()[0] != "Z"
    except OSError:
        return True


def test_a_helper_that_cannot_start_leaves_the_run_alone(monkeypatch, tmp_path):
    missing = str(tmp_path / "no-such-python")
    monkeypatch.setattr(CompileAhead, "command", lambda self: [missing])
    with compiling_ahead(threads=2) as ahead:
        assert ahead.start() is False and ahead.process is None
        assert ahead.start() is False  # not tried again


def _compiled_kernels_script() -> str:
    """A decomposition in a fresh process, printing the torchiid functions numba compiled."""
    return textwrap.dedent(
        """
        import json, sys
        import torchiid.openmp
        import torch
        from numba.core import event
        compiled = []
        class Listener(event.Listener):
            def on_start(self, ev):
                f = ev.data["dispatcher"].py_func
                if f.__module__.startswith("torchiid."):
                    compiled.append(f.__name__)
            def on_end(self, ev):
                pass
        event.register("numba:compile", Listener())
        from torchiid.model import decompose
        from torchiid.params import Parameters
        from torchiid.synthetic import mondrian
        torch.set_num_threads(2)
        decompose(mondrian(96, 128).image, Parameters().replace(iterations=2))
        print(json.dumps(sorted(set(compiled))))
        """
    )


@pytest.mark.slow
def test_a_decomposition_loads_what_the_helper_compiled(tmp_path):
    from torchiid.priors.kernel_runtime import compiled

    if compiled() is None:
        pytest.skip("the compiled kernels are off (no numba or TORCHIID_KERNELS=torch)")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}  # a first run's cache
    env.pop("OMP_NUM_THREADS", None)  # the suite's one thread per test process
    helper = [sys.executable, "-m", "torchiid.pipeline.compile_ahead", "--threads", "2"]
    subprocess.run(helper, env=env, check=True, timeout=600)
    script = tmp_path / "decompose.py"
    script.write_text(_compiled_kernels_script())
    run = subprocess.run(
        [sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr
    kernels = set(json.loads(run.stdout.strip().splitlines()[-1]))
    assert kernels, "the decomposition compiled nothing: the cache was not a first run's"
    assert "_matting_weights" in kernels  # Stage 1's kernels are the run's own to compile
    assert not kernels & STAGE2_KERNELS  # Stage 2's came from the helper's cache entries
