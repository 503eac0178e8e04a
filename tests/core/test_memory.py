import os
import subprocess
import sys

import pytest

CODE = "from torchiid.core.memory import undo_malloc_trim_threshold as u; print(u())"


def _run(env_extra):
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", CODE], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_thresholds_are_set_only_where_dask_set_the_variable():
    assert _run({"MALLOC_TRIM_THRESHOLD_": "65536"}) == "True"
    assert _run({}) == "False"


ARENAS = """
import ctypes, sys, threading
from torchiid.core.memory import share_one_malloc_arena as share
made = share() if sys.argv[1] == "share" else None
def work():
    blocks = [bytearray(200_000) for _ in range(8)]  # malloc'd, below the mmap threshold
    del blocks
threads = [threading.Thread(target=work) for _ in range(4)]
for t in threads:
    t.start()
for t in threads:
    t.join()
sys.stderr.flush()
ctypes.CDLL(None).malloc_stats()  # one "Arena N:" block per arena, on stderr
print(made)
"""


def _arenas(mode, env_extra=None):
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    env.update(env_extra or {})
    out = subprocess.run(
        [sys.executable, "-c", ARENAS, mode], env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip(), out.stderr.count("Arena ")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_one_arena_serves_every_thread_started_after_it():
    made, arenas = _arenas("share")
    assert (made, arenas) == ("True", 1)
    _, arenas = _arenas("leave")
    assert arenas > 1  # glibc's default: each new thread that allocates gets its own


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_a_malloc_arena_max_from_the_environment_is_left_alone():
    made, arenas = _arenas("share", {"MALLOC_ARENA_MAX": "2"})
    assert made == "False" and arenas <= 2
