"""How much memory is left, and the refusal of a decomposition that cannot fit in it."""

from __future__ import annotations

import cv2
import pytest
from skimage import data

import torchiid.model as model
import torchiid.pipeline.memory as memory
from torchiid.cli import main
from torchiid.core.exceptions import MemoryLimitError, ParameterError, TorchiidError
from torchiid.core.memory import available_memory, memory_limit
from torchiid.model import check_memory, decompose, memory_needed
from torchiid.params import Parameters
from torchiid.synthetic import mondrian

GB = 1 << 30


def _meminfo(tmp_path, available_kb: int):
    p = tmp_path / "meminfo"
    p.write_text(f"MemTotal:       99999999 kB\nMemFree: 1 kB\nMemAvailable:   {available_kb} kB\n")
    return p


def _available(tmp_path, cgroup: str, groups: dict[str, dict[str, object]], free_gb: int = 16):
    """``available_memory`` of a machine with ``free_gb`` GB available and these cgroup files.

    ``cgroup`` is the text of ``/proc/self/cgroup``; ``groups`` maps a folder under the
    cgroup root (``"memory/jobs"``) to its files and their contents.
    """
    cg = tmp_path / "cgroup"
    cg.write_text(cgroup)
    root = tmp_path / "sys"
    for rel, files in groups.items():
        where = root / rel
        where.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            (where / name).write_text(str(text))
    return available_memory(_meminfo(tmp_path, free_gb * 1024 * 1024), cg, root)


def test_available_memory_is_memavailable_without_a_cgroup_limit(tmp_path):
    groups = {"user.slice": {"memory.max": "max", "memory.current": 123}}
    assert _available(tmp_path, "0::/user.slice\n", groups, free_gb=5) == 5 * GB


def test_a_cgroup_v2_limit_counts_usage_without_its_reclaimable_cache(tmp_path):
    stat = "anon 100\ninactive_file 1073741824\nactive_file 5\n"
    groups = {"docker/abc": {"memory.max": 4 * GB, "memory.current": 3 * GB, "memory.stat": stat}}
    # the container's 4 GB less 3 GB used, of which 1 GB reclaimable cache: 2 GB, below the
    # machine's 16 GB
    assert _available(tmp_path, "0::/docker/abc\n", groups) == 2 * GB


def test_a_cgroup_v1_limit_on_an_ancestor_counts(tmp_path):
    groups = {
        "memory/jobs/42": {
            "memory.limit_in_bytes": (1 << 63) - 4096,  # v1's "no limit"
            "memory.usage_in_bytes": GB,
        },
        "memory/jobs": {
            "memory.limit_in_bytes": 3 * GB,
            "memory.usage_in_bytes": 2 * GB,
            "memory.stat": "cache 7\ntotal_inactive_file 0\n",
        },
    }
    assert _available(tmp_path, "9:cpu:/\n4:memory:/jobs/42\n0::/\n", groups) == GB


def test_cgroup_v1_prefers_the_subtree_cache_listed_after_the_groups_own(tmp_path):
    # the kernel lists inactive_file (the group's own pages) before total_inactive_file (the
    # subtree's, which its usage covers): the subtree's counts
    stat = "cache 1\ninactive_file 0\ntotal_cache 2\ntotal_inactive_file 2147483648\n"
    groups = {
        "memory/job": {
            "memory.limit_in_bytes": 4 * GB,
            "memory.usage_in_bytes": 3 * GB,
            "memory.stat": stat,
        }
    }
    assert _available(tmp_path, "4:memory:/job\n", groups) == 3 * GB


def test_cgroup_v2_soft_limit_and_an_unlimited_leaf_under_a_limited_parent(tmp_path):
    groups = {
        "slice/leaf": {"memory.max": "max", "memory.current": 5},
        "slice": {"memory.max": 8 * GB, "memory.high": 6 * GB, "memory.current": GB},
    }
    # the parent's memory.high (6 GB), the lower of its two limits, less its 1 GB
    assert _available(tmp_path, "0::/slice/leaf\n", groups) == 5 * GB


def test_unreadable_or_garbled_files_are_skipped_not_raised(tmp_path):
    cg = tmp_path / "cgroup"
    cg.write_bytes("0::/caf\u00e9.scope\n".encode())
    root = tmp_path / "sys"
    root.mkdir()
    (root / "memory.max").write_bytes(b"\xff\xfe not a number\n")
    meminfo = tmp_path / "meminfo"
    meminfo.write_bytes(b"MemAvailable: \xff kB\nMemFree: 7 kB\n")
    assert available_memory(meminfo, cg, root) is None
    # a good MemAvailable still counts beside a garbled cgroup
    assert available_memory(_meminfo(tmp_path, 1024), cg, root) == 1024 * 1024


def test_nothing_readable_means_unknown(tmp_path):
    assert available_memory(tmp_path / "no", tmp_path / "no", tmp_path / "no") is None


def test_the_estimate_grows_with_the_working_resolution_and_the_stored_state():
    default, converged = Parameters(), Parameters.preset("converged")
    base = model.MEMORY_OVERHEAD
    small = memory_needed(384, 512, default) - base
    # at the default working resolution a 12 MP photo costs its full-resolution layers more
    # than a 512 px one, under a GB (measured: 1.33 GB peak for the whole process)
    assert 0 < memory_needed(3024, 4032, default) - base - small < 1e9
    # at full resolution it grows in proportion to the pixels, and more with a stored state
    full = memory_needed(3024, 4032, default.replace(max_side=0)) - base
    assert full == pytest.approx(small * 3024 * 4032 / (384 * 512), rel=1e-3)
    assert memory_needed(3024, 4032, converged.replace(max_side=0)) - base > 1.4 * full
    assert memory_needed(384, 512, default, batch=3) - base == 3 * small


def test_decompose_refuses_before_any_work_what_cannot_fit(monkeypatch):
    img = mondrian(96, 128).image
    p = Parameters().replace(iterations=1, max_side=0)
    need = memory_needed(96, 128, p)
    monkeypatch.setattr(memory, "available_memory", lambda: need - 1)

    def no_work(*args, **kwargs):  # pragma: no cover - must not be reached
        raise AssertionError("the features were computed")

    monkeypatch.setattr(model, "semantic_features", no_work)
    with pytest.raises(MemoryLimitError) as err:
        decompose(img, p)
    msg = str(err.value)
    assert isinstance(err.value, TorchiidError)
    assert "128x96 px at full resolution" in msg and "is available" in msg
    assert "set TORCHIID_MEMORY_CHECK=0 to try anyway" in msg


def test_the_message_names_the_default_working_resolution_when_it_would_fit(monkeypatch):
    img = mondrian(600, 800).image
    full = Parameters().replace(iterations=1, max_side=0)
    flags = {"return_stage1": True}  # decompose's default
    at_default = memory_needed(600, 800, **flags)
    monkeypatch.setattr(memory, "available_memory", lambda: at_default + 1)
    with pytest.raises(MemoryLimitError) as err:
        decompose(img, full)
    assert "; with --max-side 512, the default" in str(err.value)
    # where even that would not fit, the message says so
    monkeypatch.setattr(memory, "available_memory", lambda: at_default - 1)
    with pytest.raises(MemoryLimitError) as err:
        decompose(img, full)
    assert "even with --max-side 512" in str(err.value)


def test_the_estimate_counts_what_the_caller_asks_to_keep():
    p = Parameters().replace(max_side=0)
    plain = memory_needed(600, 800, p)
    assert memory_needed(600, 800, p, return_stage1=True) == plain + 16 * 600 * 800
    with_layers = memory_needed(600, 800, p, return_iterations=True)
    assert with_layers == plain + 32 * p.iterations * 600 * 800


def test_a_failing_memory_probe_never_stops_a_decomposition(monkeypatch):
    def broken():
        raise RuntimeError("no /proc here")

    monkeypatch.setattr(memory, "available_memory", broken)
    p = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)
    out = decompose(mondrian(64, 64).image, p)
    assert out.reflectance.shape == (1, 3, 64, 64)


def test_the_check_can_be_switched_off_and_does_not_touch_what_fits(monkeypatch):
    img = mondrian(64, 64).image
    p = Parameters().replace(iterations=1, use_sc=False, use_sm=False, use_rm=False)
    monkeypatch.setattr(memory, "available_memory", lambda: 1)
    monkeypatch.setenv("TORCHIID_MEMORY_CHECK", "0")
    out = decompose(img, p)
    assert out.reflectance.shape == (1, 3, 64, 64)
    # unknown memory (not Linux): no check
    monkeypatch.delenv("TORCHIID_MEMORY_CHECK")
    monkeypatch.setattr(memory, "available_memory", lambda: None)
    decompose(img, p)


def test_cli_fails_only_the_photo_that_cannot_fit(tmp_path, monkeypatch, capsys):
    small = cv2.resize(data.chelsea(), (96, 72), interpolation=cv2.INTER_AREA)
    big = cv2.resize(data.coffee(), (240, 160), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "small.png"), small[..., ::-1])
    cv2.imwrite(str(tmp_path / "big.png"), big[..., ::-1])
    p = Parameters().replace(max_side=0)
    between = (memory_needed(72, 96, p) + memory_needed(160, 240, p)) // 2
    monkeypatch.setattr(memory, "available_memory", lambda: between)
    out = tmp_path / "out"
    argv = ["decompose", str(tmp_path), "-o", str(out), "--max-side", "0"]
    status = main([*argv, "--iterations", "1", "--no-progress"])
    assert status == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("torchiid: error:")]
    assert len(lines) == 1 and "big.png" in lines[0]
    assert "240x160 px at full resolution needs about" in lines[0]
    assert "Traceback" not in err
    assert (out / "small-reflectance.png").exists()
    assert not list(out.glob("big-*"))
    # not a bad input: with memory to spare (or the check off) a rerun decomposes it
    monkeypatch.setattr(memory, "available_memory", lambda: None)
    status = main([*argv, "--iterations", "1", "--no-progress"])
    assert status == 0
    assert (out / "big-reflectance.png").exists()


def test_a_memory_limit_is_read_in_gb_from_the_environment_or_given(monkeypatch):
    monkeypatch.delenv("TORCHIID_MEMORY_LIMIT", raising=False)
    assert memory_limit() is None
    monkeypatch.setenv("TORCHIID_MEMORY_LIMIT", " 2.5 ")
    assert memory_limit() == 2_500_000_000
    monkeypatch.setenv("TORCHIID_MEMORY_LIMIT", "0")  # 0: no cap
    assert memory_limit() is None
    assert memory_limit(0.25) == 250_000_000
    monkeypatch.setenv("TORCHIID_MEMORY_LIMIT", "4GB")
    with pytest.raises(ParameterError, match="TORCHIID_MEMORY_LIMIT must be a number of GB"):
        memory_limit()
    for bad in ("-1", "nan", "inf"):
        with pytest.raises(ParameterError, match="the memory limit must be"):
            memory_limit(bad)


def test_a_memory_limit_caps_what_is_available_and_the_message_says_how_to_raise_it(
    monkeypatch,
):
    img = mondrian(96, 128).image
    p = Parameters().replace(iterations=1, max_side=0)
    need = memory_needed(96, 128, p, return_stage1=True)

    def no_work(*args, **kwargs):  # pragma: no cover - must not be reached
        raise AssertionError("the features were computed")

    monkeypatch.setattr(model, "semantic_features", no_work)
    monkeypatch.setattr(memory, "available_memory", lambda: 100 * need)
    monkeypatch.setenv("TORCHIID_MEMORY_LIMIT", str((need - 1_000_000) / 1e9))
    with pytest.raises(MemoryLimitError) as err:
        decompose(img, p)
    msg = str(err.value)
    assert "over the memory limit of" in msg and "is available" not in msg
    assert "--memory-limit GB, or TORCHIID_MEMORY_LIMIT" in msg
    # switching the check off does not lift a cap the user set
    monkeypatch.setenv("TORCHIID_MEMORY_CHECK", "0")
    with pytest.raises(MemoryLimitError, match="memory limit"):
        decompose(img, p)
    monkeypatch.delenv("TORCHIID_MEMORY_CHECK")
    # a cap above what is left: what is left counts
    monkeypatch.setenv("TORCHIID_MEMORY_LIMIT", str(100 * need / 1e9))
    monkeypatch.setattr(memory, "available_memory", lambda: need - 1)
    with pytest.raises(MemoryLimitError, match="is available"):
        decompose(img, p)


def test_check_memory_takes_an_explicit_limit_over_the_environment(monkeypatch):
    monkeypatch.setattr(memory, "available_memory", lambda: None)
    monkeypatch.setenv("TORCHIID_MEMORY_LIMIT", "1000")
    p = Parameters()
    need = memory_needed(3024, 4032, p)
    check_memory(3024, 4032, p)  # under the environment's 1000 GB
    check_memory(3024, 4032, p, limit=need)
    with pytest.raises(MemoryLimitError, match=r"4032x3024 px at 512x384 px needs about"):
        check_memory(3024, 4032, p, limit=need - 1)


def test_figures_in_messages_keep_their_first_digits():
    from torchiid.pipeline.memory import _gb

    assert [_gb(n) for n in (1e6, 1e7, 2.5e8, 31.6e9)] == [
        "0.001 GB",
        "0.01 GB",
        "0.25 GB",
        "31.6 GB",
    ]
