"""Saying that the kernels compile: only for torchiid's functions, only on a cache miss."""

from __future__ import annotations

import importlib.util

import pytest

from torchiid.core.first_compile import notify_first_compile, watch_compilation

numba = pytest.importorskip("numba")

KERNEL = "from numba import njit\n\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n"


def _load(source, name):
    """The module in ``source`` under ``name``: a new dispatcher each time (numba's cache on
    disk beside the file is what they share)."""
    spec = importlib.util.spec_from_file_location(name, source)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_compilation_is_said_once_and_a_load_from_the_cache_is_not(tmp_path):
    source = tmp_path / "probe_kernels.py"
    source.write_text(KERNEL)
    watch_compilation()
    said = []
    with notify_first_compile(lambda: said.append("first")):
        kernels = _load(source, "torchiid.probe_kernels")
        assert kernels.twice(2) == 4  # compiled for int64
        assert kernels.twice(2.5) == 5.0  # and for float64: still said once
    assert said == ["first"]
    with notify_first_compile(lambda: said.append("second")):
        again = _load(source, "torchiid.probe_kernels")
        assert again.twice(3) == 6 and again.twice(3.5) == 7.0  # from numba's cache
    assert said == ["first"]
    assert kernels.twice(1j) == 2j  # compiled, but no block is waiting: nothing said
    assert said == ["first"]


def test_another_library_s_compilation_is_not_torchiid_s(tmp_path):
    source = tmp_path / "other_kernels.py"
    source.write_text(KERNEL)
    watch_compilation()
    said = []
    with notify_first_compile(lambda: said.append(1)):
        assert _load(source, "other_kernels").twice(4) == 8
    assert said == []


def test_nested_blocks_each_hear_of_it_once(tmp_path):
    source = tmp_path / "nested_kernels.py"
    source.write_text(KERNEL)
    watch_compilation()
    watch_compilation()  # registered once however often it is called
    said = []
    with notify_first_compile(lambda: said.append("outer")):
        with notify_first_compile(lambda: said.append("inner")):
            kernels = _load(source, "torchiid.nested_kernels")
            kernels.twice(1)
            kernels.twice(1.0)
    assert sorted(said) == ["inner", "outer"]


def test_a_note_that_fails_does_not_stop_the_compilation(tmp_path):
    source = tmp_path / "failing_note_kernels.py"
    source.write_text(KERNEL)
    watch_compilation()

    def broken_pipe():
        raise BrokenPipeError("stderr is closed")

    with notify_first_compile(broken_pipe):
        assert _load(source, "torchiid.failing_note_kernels").twice(5) == 10
