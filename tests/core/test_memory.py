import os
import platform
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


TRIM = """
import ctypes, os, sys
from torchiid.core.memory import release_free_memory
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
# 64 MB in 64 KiB blocks (below the mmap threshold: on the heap), touched, then all freed but
# the last, which keeps the heap's top in use: glibc holds the rest until it is trimmed
blocks = [libc.malloc(65536) for _ in range(1000)]
for b in blocks:
    ctypes.memset(b, 1, 65536)
for b in blocks[:-1]:
    libc.free(b)
held = rss()
done = release_free_memory() if sys.argv[1] == "release" else None
print(done, (held - rss()) / 1e6)
"""


def _trim(mode):
    out = subprocess.run([sys.executable, "-c", TRIM, mode], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    done, freed = out.stdout.split()
    return done, float(freed)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_free_memory_below_memory_in_use_goes_back_to_the_system():
    done, freed = _trim("release")
    assert done == "True" and freed > 40  # of the 64 MB freed
    _, freed = _trim("keep")
    assert freed < 5  # without it glibc holds them


def test_decompose_releases_free_memory_after_stage0_the_half_size_run_and_the_shading(
    monkeypatch,
):
    import torchiid.model as model
    from torchiid.params import Parameters
    from torchiid.pipeline.alternation import Alternation
    from torchiid.synthetic import mondrian

    calls = []
    monkeypatch.setattr(model, "release_free_memory", lambda: calls.append(1) or True)
    kept_terms = []  # (alternation, shading terms kept) as each reflectance step starts
    step = Alternation.reflectance_step

    def reflectance_step(self, k, reflectance):
        kept_terms.append((k, len(self.shading_cache.terms)))
        return step(self, k, reflectance)

    monkeypatch.setattr(Alternation, "reflectance_step", reflectance_step)
    image = mondrian(128, 128).image
    model.decompose(image, Parameters().replace(iterations=2))
    # Stage 0; the half-size alternation; the last shading solve's terms
    assert len(calls) == 3
    assert kept_terms[0][1] > 0 and kept_terms[-1] == (2, 0)
    calls.clear()
    kept_terms.clear()
    model.decompose(image, Parameters().replace(iterations=2, coarse_scale=1.0))
    assert len(calls) == 2
    assert kept_terms[0][0] == 1 and kept_terms[0][1] > 0 and kept_terms[1] == (2, 0)
