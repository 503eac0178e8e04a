"""One grammar for every command: version, help, run options, exit statuses, verbosity.

Also what makes the command line start at once: ``torchiid --help``, ``--version`` and every
``torchiid COMMAND --help`` import neither torch nor the other heavy libraries (checked in a
fresh process: a property, not a timing; ``tools/bench_startup.py`` times it).
"""

import ast
import importlib
import importlib.metadata
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage import data

import torchiid
from torchiid.cli import COMMANDS, build_parser, main
from torchiid.core.exceptions import TorchiidError
from torchiid.params import Parameters
from torchiid.pipeline.compile_ahead import CompileAhead

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--iterations", "1", "--no-progress"]
HEAVY = ("torch", "numba", "cv2", "kornia", "skimage", "onnxruntime", "av", "numpy", "scipy", "PIL")
LONG = [c for c in COMMANDS if c.runs_long]


@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    d = tmp_path_factory.mktemp("photo")
    cat = cv2.resize(data.chelsea(), (96, 72), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(d / "cat.png"), cat[..., ::-1])
    (d / "frames").mkdir()
    cv2.imwrite(str(d / "frames" / "f1.png"), cat[..., ::-1])
    return d


# ----------------------------------------------------------------------------- version


def test_the_package_and_the_code_agree_on_a_version_of_at_least_1_0_0(capsys):
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert project["project"]["version"] == torchiid.__version__
    major, minor, patch = torchiid.__version__.split(".")
    assert (int(major), int(minor), int(patch)) >= (1, 0, 0)  # semantic versioning
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"torchiid {torchiid.__version__}"


def test_files_record_the_version_that_wrote_them(photo, tmp_path):
    out = tmp_path / "out"
    assert main(["decompose", str(photo / "cat.png"), "-o", str(out), *FAST]) == 0
    info = json.loads((out / "cat-info.json").read_text())
    line = json.loads((out / "manifest.jsonl").read_text().splitlines()[-1])
    assert info["torchiid_version"] == line["torchiid_version"] == torchiid.__version__
    argv = ["decompose", str(photo / "cat.png"), "--method", "retinex", "--no-progress"]
    assert main([*argv, "-o", str(tmp_path / "retinex")]) == 0
    params = json.loads((tmp_path / "retinex" / "cat-params.json").read_text())
    assert params["torchiid_version"] == torchiid.__version__


# ----------------------------------------------------------------------------- start-up


def test_help_and_version_import_nothing_heavy():
    """Every help page and --version, each in the same fresh process, loads no heavy module."""
    pages = [["--help"], ["--version"], *([c.name, "--help"] for c in COMMANDS)]
    code = f"""
import sys
from torchiid.cli import main
for argv in {pages!r}:
    try:
        main(argv)
    except SystemExit as stop:
        assert stop.code == 0, (argv, stop.code)
    loaded = [m for m in {HEAVY!r} if m in sys.modules]
    assert not loaded, (argv, loaded)
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith("ok")


def test_import_torchiid_is_lazy_and_every_public_name_resolves():
    code = """
import sys
import torchiid
assert "torch" not in sys.modules
from torchiid import Parameters, decompose, edit, TorchiidError
import torchiid.model, torchiid.params
assert decompose is torchiid.model.decompose and Parameters is torchiid.params.Parameters
assert edit.merge and TorchiidError.__module__ == "torchiid.core.exceptions"
missing = [n for n in torchiid.__all__ if getattr(torchiid, n, None) is None]
assert not missing, missing
assert set(torchiid.__all__) <= set(dir(torchiid))
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        torchiid.nothing_here  # noqa: B018


def test_static_tools_see_every_public_name():
    """``__all__`` is a literal and each name is imported under ``if TYPE_CHECKING:``."""
    tree = ast.parse((ROOT / "torchiid" / "__init__.py").read_text())
    listed = typed = None
    for node in tree.body:
        if isinstance(node, ast.Assign) and node.targets[0].id == "__all__":
            listed = set(ast.literal_eval(node.value))
        if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
            typed = {a.asname or a.name for i in node.body for a in i.names}
    assert listed and listed == typed == set(torchiid.__all__)


LAZY_PACKAGES = ("torchiid.core", "torchiid.io", "torchiid.collection")
SUBMODULES = {"torchiid.core": "device", "torchiid.io": "layers", "torchiid.collection": "job"}


@pytest.mark.parametrize("name", LAZY_PACKAGES)
def test_lazy_packages_resolve_every_name_and_show_them_to_static_tools(name):
    """Each name of ``__all__`` loads, has a source, and is imported under TYPE_CHECKING."""
    package = importlib.import_module(name)
    assert set(package._SOURCES) == set(package.__all__)
    for public in package.__all__:
        value = getattr(package, public)
        assert getattr(importlib.import_module(package._SOURCES[public]), public) is value
    assert set(package.__all__) <= set(dir(package))
    with pytest.raises(AttributeError, match="has no attribute 'nothing_here'"):
        package.nothing_here  # noqa: B018
    code = f"import {name} as p, {name}.{SUBMODULES[name]} as m; print(p.{SUBMODULES[name]} is m)"
    first = f"import {name} as p; print(p.{SUBMODULES[name]}.__name__)"
    for line, expected in ((code, "True"), (first, f"{name}.{SUBMODULES[name]}")):
        done = subprocess.run([sys.executable, "-c", line], capture_output=True, text=True)
        assert done.stdout.strip() == expected, done.stderr[-2000:]  # a submodule, on access
    path = ROOT / Path(*name.split(".")) / "__init__.py"
    tree = ast.parse(path.read_text())
    typed = {
        a.asname or a.name
        for node in tree.body
        if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING"
        for i in node.body
        for a in i.names
    }
    assert typed == set(package.__all__)


def test_a_rerun_that_finds_every_input_done_loads_no_model(tmp_path):
    """Planning from the manifest needs no torch: a done folder is skipped at once."""
    photo = tmp_path / "cat.png"
    cv2.imwrite(str(photo), cv2.resize(data.chelsea(), (96, 72))[..., ::-1])
    argv = ["decompose", str(photo), "-o", str(tmp_path / "out"), "--iterations", "1"]
    assert main([*argv, "--no-progress", "-q"]) == 0
    code = f"""
import sys
from torchiid.cli import main
assert main({[*argv, "--no-progress"]!r}) == 0
loaded = [m for m in {HEAVY!r} if m in sys.modules]
assert not loaded, loaded
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith("ok")
    assert "0 done, 1 skipped, 0 failed" in done.stderr
    # a new input in the same folder is decomposed as before (the model loads then)
    other = tmp_path / "cat2.png"
    other.write_bytes(photo.read_bytes())
    argv[1:2] = [str(photo), str(other)]
    assert main([*argv, "--no-progress", "-q"]) == 0
    assert (tmp_path / "out" / "cat2-reflectance.png").is_file()


def test_choices_named_for_help_are_the_library_s():
    from torchiid import edit
    from torchiid.commands import edit as edit_command
    from torchiid.commands import eval as eval_command
    from torchiid.commands import video as video_command
    from torchiid.eval.runner import METHODS
    from torchiid.eval.scoring import DATASETS
    from torchiid.video.flow import FLOW_METHODS
    from torchiid.video.temporal import DEFAULT_TEMPORAL_WEIGHT

    assert edit_command.COMBINE == edit.COMBINE
    assert eval_command.DATASETS == DATASETS and eval_command.METHODS == METHODS
    assert video_command.FLOW_METHODS == FLOW_METHODS
    assert video_command.DEFAULT_TEMPORAL_WEIGHT == DEFAULT_TEMPORAL_WEIGHT


# ----------------------------------------------------------------------------- grammar


def test_help_lists_every_command_on_one_line(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for command in COMMANDS:
        pattern = rf"\s+{re.escape(command.name)}\s+{re.escape(command.help)}"
        assert len([x for x in text.splitlines() if re.fullmatch(pattern, x)]) == 1, command
    assert "exit status: 0 done; 1 failed" in text and "130 interrupted" in text


# the smallest command line of each command that runs long
MINIMAL = {
    "decompose": ["x.png", "-o", "out"],
    "decompose-video": ["frames", "-o", "out"],
    "edit": ["merge", "x.png", "-o", "out"],
    "eval": ["mit", "data"],
    "features": ["x.png", "-o", "out"],
    "app": [],
}


@pytest.mark.parametrize("command", LONG, ids=lambda c: c.name)
def test_every_long_command_takes_the_run_options(command):
    parser = build_parser()
    base = [command.name, *MINIMAL[command.name]]
    args = parser.parse_args([*base, "--no-progress", "--device", "cpu", "--threads", "3", "-q"])
    assert (args.no_progress, args.device, args.threads, args.quiet) == (True, "cpu", 3, True)
    assert parser.parse_args(base).threads is None
    assert parser.parse_args([*base, "-v"]).verbose and parser.parse_args(["-v", *base]).verbose
    assert parser.parse_args(["--quiet", *base]).quiet
    assert not parser.parse_args(base).verbose


@pytest.mark.parametrize("argv", [["--threads", "0"], ["--threads", "two"], ["--device", "tpu"]])
def test_bad_run_options_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["decompose", "x.png", "-o", "out", *argv])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("torchiid: error: argument ") and "usage:" not in err
    assert err.endswith(" (see 'torchiid decompose --help')\n") and err.count("\n") == 1


def test_an_unknown_option_names_the_command_s_help(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["decompose", "x.png", "-o", "out", "--bogus", "1"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert (
        err
        == "torchiid: error: unrecognized arguments: --bogus 1 (see 'torchiid decompose --help')\n"
    )


def test_quiet_and_verbose_exclude_each_other(capsys):
    base = ["decompose", "x.png", "-o", "out"]
    for argv in (["-q", "-v", *base], [*base, "-q", "-v"], ["-q", *base, "-v"]):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
        assert re.search(r"not allowed with|exclude each other", capsys.readouterr().err)


# ----------------------------------------------------------------------------- exit statuses


def _argv(command: str, photo: Path, out: Path) -> list[str]:
    return {
        "decompose": ["decompose", str(photo / "cat.png"), "-o", str(out)],
        "decompose-video": ["decompose-video", str(photo / "frames"), "-o", str(out)],
        "edit": ["edit", "merge", str(photo / "cat.png"), "-o", str(out)],
        "eval": ["eval", "mit", str(photo), "-o", str(out)],
        "features": ["features", str(photo / "cat.png"), "-o", str(out)],
        "app": ["app", "--port", "1"],
    }[command]


def _fail_early(monkeypatch, command: str, exc: BaseException) -> None:
    """Make ``command`` raise ``exc`` as its work starts."""

    def fail(*args, **kwargs):
        raise exc

    if command == "features":
        import torchiid.core.device

        monkeypatch.setattr(torchiid.core.device, "resolve_device", fail)
    elif command == "app":
        monkeypatch.setattr("torchiid.commands.app.gradio_installed", fail)
    else:
        module = next(c.module for c in COMMANDS if c.name == command)
        monkeypatch.setattr(f"torchiid.commands.{module}.params_from_args", fail)


@pytest.mark.parametrize("command", [c.name for c in LONG])
@pytest.mark.parametrize(
    ("exc", "status", "line"),
    [
        (KeyboardInterrupt(), 130, "torchiid: interrupted"),
        (TypeError("a bug"), 1, "torchiid: error: internal error (TypeError: a bug); rerun"),
        (TorchiidError("a bad setting"), 2, "torchiid: error: a bad setting"),
    ],
    ids=["interrupted", "internal-error", "set-up-error"],
)
def test_exit_statuses_are_the_same_for_every_command(
    photo, tmp_path, monkeypatch, capsys, command, exc, status, line
):
    _fail_early(monkeypatch, command, exc)
    assert main([*_argv(command, photo, tmp_path / "out"), "--no-progress"]) == status
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(line)
    assert "Traceback" not in err[0] and not (tmp_path / "out").exists()


def test_usage_errors_exit_with_2_for_every_command(photo, tmp_path, capsys):
    for command in LONG:
        with pytest.raises(SystemExit) as stop:
            main([*_argv(command.name, photo, tmp_path / "out"), "--no-such-option"])
        assert stop.value.code == 2, command.name
        assert "unrecognized arguments: --no-such-option" in capsys.readouterr().err


def test_verbose_adds_the_traceback_of_an_internal_error(photo, tmp_path):
    code = """
import sys
import torchiid.commands.decompose as command
from torchiid.cli import main
def bug(args):
    raise TypeError("a bug")
command.params_from_args = bug
sys.exit(main(sys.argv[1:]))
"""
    argv = [*_argv("decompose", photo, tmp_path / "out"), "--no-progress"]
    quiet = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True)
    loud = subprocess.run([sys.executable, "-c", code, *argv, "-v"], capture_output=True, text=True)
    assert quiet.returncode == loud.returncode == 1
    assert "Traceback" not in quiet.stderr and "internal error (TypeError: a bug)" in quiet.stderr
    assert "Traceback" in loud.stderr and "in bug\nTypeError: a bug" in loud.stderr


def test_a_broken_torch_installation_is_a_set_up_error_that_names_it(photo, tmp_path):
    fake = tmp_path / "site" / "torch"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text(
        'raise ImportError("libtorch_cpu.so: cannot open shared object file")\n'
    )
    paths = [str(fake.parent), str(ROOT), os.environ.get("PYTHONPATH", "")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in paths if p)}
    out = tmp_path / "out"
    argv = ["decompose", str(photo), "-o", str(out), "--no-progress"]
    code = "import sys; from torchiid.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, env=env, cwd=ROOT
    )
    assert done.returncode == 2, done.stderr
    # the same torch again, as PyPI names its version, without touching the rest
    pinned = "torch==" + importlib.metadata.version("torch").partition("+")[0]
    assert done.stderr.strip().splitlines()[-1] == (
        "torchiid: error: torch is installed but cannot be imported (libtorch_cpu.so: cannot "
        f"open shared object file); reinstall it: pip install --force-reinstall --no-deps {pinned}"
    )
    assert "Traceback" not in done.stderr and not out.exists()


def test_threads_are_set_for_the_run_and_restored(photo, tmp_path, monkeypatch):
    import os

    import torch

    before, seen = torch.get_num_threads(), {}

    def record(args):
        seen["torch"], seen["omp"] = torch.get_num_threads(), os.environ.get("OMP_NUM_THREADS")
        raise TorchiidError("stop here")

    monkeypatch.setattr("torchiid.commands.edit.params_from_args", record)
    omp = os.environ.get("OMP_NUM_THREADS")
    argv = [*_argv("edit", photo, tmp_path / "out"), "--threads", "3"]
    assert main(argv) == 2
    assert seen == {"torch": 3, "omp": "3"}
    assert torch.get_num_threads() == before and os.environ.get("OMP_NUM_THREADS") == omp


def test_only_the_console_script_sets_the_process_allocator(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr("torchiid.core.memory.share_one_malloc_arena", lambda: calls.append(1))
    argv = ["decompose", str(tmp_path / "missing.png"), "-o", str(tmp_path / "out"), "-q"]
    assert main(argv) == 1  # called from Python: the caller's process keeps its allocator
    assert calls == []
    assert main(argv, own_process=True) == 1
    assert calls == [1]


# ----------------------------------------------------------------------------- verbosity


def test_the_default_preset_s_caps_are_no_news(photo, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["decompose", str(photo / "cat.png"), "-o", str(out), *FAST]) == 0
    err = capsys.readouterr().err
    assert "tolerance" not in err and err.count("\n") == 1  # the summary line alone
    info = json.loads((out / "cat-info.json").read_text())
    assert info["converged"] is False and len(info["solves"]) == 2  # recorded there
    assert main(["decompose", str(photo / "cat.png"), "-o", str(tmp_path / "v"), *FAST, "-v"]) == 0
    err = capsys.readouterr().err
    assert "cat.png: 2 of 2 solver runs stopped before their tolerance (the preset's caps" in err


def test_negatives_set_to_0_are_a_note_and_recorded(photo, tmp_path, capsys):
    linear = (cv2.imread(str(photo / "cat.png"))[..., ::-1] / 255.0).astype(np.float32) ** 2.2
    linear[3, 4, 1] = -0.01  # a renderer's ringing beside an edge
    np.save(tmp_path / "render.npy", linear)
    out = tmp_path / "out"
    assert main(["decompose", str(tmp_path / "render.npy"), "-o", str(out), *FAST]) == 0
    err = capsys.readouterr().err
    assert (
        "torchiid: note: " in err and "render.npy: 1 negative value (down to -0.01) set to 0" in err
    )
    assert json.loads((out / "render-info.json").read_text())["negatives_set_to_zero"] == 1


def test_a_large_declared_size_fails_before_its_pixels_are_decoded(tmp_path, monkeypatch, capsys):
    import struct
    import zlib

    import torchiid.collection.job as job

    ihdr = b"IHDR" + struct.pack(">IIBBBBB", 30000, 20000, 8, 2, 0, 0, 0)
    end = struct.pack(">I", 0) + b"IEND" + struct.pack(">I", zlib.crc32(b"IEND"))
    png = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + ihdr + struct.pack(">I", zlib.crc32(ihdr))
    png += end
    (tmp_path / "declared.png").write_bytes(png)  # a few bytes, 600 million pixels declared

    def never(*args, **kwargs):
        raise AssertionError("decoded")

    monkeypatch.setattr(job, "load_image", never)
    argv = ["decompose", str(tmp_path / "declared.png"), "-o", str(tmp_path / "out")]
    assert main([*argv, *FAST, "--memory-limit", "2"]) == 1
    err = capsys.readouterr().err
    assert "declared.png: decomposing 30000x20000 px at 512x341 px needs about" in err
    assert "over the memory limit of 2.00 GB" in err


def test_settings_that_fail_every_image_stop_the_run_before_any(
    photo, tmp_path, monkeypatch, capsys
):
    argv = ["decompose", str(photo / "cat.png"), "-o", str(tmp_path / "out"), *FAST]
    monkeypatch.setenv("TORCHIID_MEMORY_LIMIT", "abc")
    assert main(argv) == 2
    assert "TORCHIID_MEMORY_LIMIT must be a number of GB >= 0" in capsys.readouterr().err
    monkeypatch.delenv("TORCHIID_MEMORY_LIMIT")
    assert main([*argv, "--max-side", "30"]) == 2
    err = capsys.readouterr().err
    assert "max_side must be 0 (no resizing) or at least patch_size (60), got 30" in err
    assert not (tmp_path / "out").exists()


def test_quiet_prints_only_errors(photo, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["decompose", str(photo / "cat.png"), "-o", str(out), *FAST, "-q"]) == 0
    assert capsys.readouterr().err == "" and (out / "cat-reflectance.png").is_file()
    argv = ["-q", "decompose", str(photo / "cat.png"), "missing.png", "-o", str(out)]
    assert main([*argv, "--iterations", "1"]) == 1  # -q: no progress bar either
    assert capsys.readouterr().err.splitlines() == [
        "torchiid: error: missing.png: no such file",
        "torchiid: 1 of 2 input(s) failed",
    ]


def test_a_capped_solve_of_the_converged_preset_is_a_note(photo, tmp_path, monkeypatch, capsys):
    import dataclasses

    import torchiid.model as model

    real = model.decompose

    def capped(*args, **kwargs):  # the solves as if the last had hit its safety cap
        result = real(*args, **kwargs)
        last = dataclasses.replace(result.solves[-1], converged=False, iterations=9, cap=9)
        return dataclasses.replace(result, solves=(*result.solves[:-1], last))

    monkeypatch.setattr(model, "decompose", capped)
    argv = ["decompose", str(photo / "cat.png"), "--preset", "converged", *FAST]
    assert main([*argv, "-o", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "torchiid: note: " in err and "1 of 2 solver runs stopped before their tolerance" in err
    assert "safety caps: raise cg_max_iter / bregman_iter" in err and "cat-info.json" in err
    assert main([*argv, "-o", str(tmp_path / "b"), "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_the_first_compilation_of_the_kernels_is_a_note_above_the_bar(
    photo, tmp_path, monkeypatch, capsys
):
    import importlib.util

    import torchiid.model as model
    from torchiid.priors.kernel_runtime import compiled

    if compiled() is None:
        pytest.skip("the compiled kernels are off (no numba or TORCHIID_KERNELS=torch)")
    source = tmp_path / "probe.py"
    source.write_text("from numba import njit\n\n\n@njit\ndef one(x):\n    return x + 1\n")
    real = model.decompose

    def compiling(*args, **kwargs):  # as on a first run: a kernel of torchiid's compiles
        spec = importlib.util.spec_from_file_location("torchiid.probe", source)
        probe = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(probe)
        probe.one(1)
        probe.one(1.0)
        return real(*args, **kwargs)

    monkeypatch.setattr(model, "decompose", compiling)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: the bar is drawn
    helpers = []  # Stage 2's compiling process (here a sleeper), one per compiling run

    def sleeper(ahead):
        helpers.append(ahead)
        return [sys.executable, "-c", "import time; time.sleep(60)"]

    monkeypatch.setattr(CompileAhead, "command", sleeper)
    argv = ["decompose", str(photo / "cat.png"), "--iterations", "1", "--preset", "paper"]
    assert main([*argv, "-o", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    note = (
        "torchiid: note: compiling the CPU kernels, once for this Python environment (up to a "
        "minute; later runs load them from numba's cache)"
    )
    assert err.count(note) == 1
    assert f"{note}\n" in err and "images:" in err.split(note)[1]  # a line; the bar below it
    assert len(helpers) == 1 and helpers[0].parameters() == Parameters.preset("paper").replace(
        iterations=1
    )  # the run's parameters
    assert helpers[0].process.wait(timeout=10) == -signal.SIGTERM  # stopped with the run
    assert main([*argv, "-o", str(tmp_path / "b"), "-q"]) == 0
    assert capsys.readouterr().err == ""
    assert len(helpers) == 2  # -q keeps the note to itself, not the helper
    monkeypatch.setattr(model, "decompose", real)  # the kernels are in the cache: no note
    assert main([*argv, "-o", str(tmp_path / "c")]) == 0
    assert "compiling" not in capsys.readouterr().err
    assert len(helpers) == 2  # nothing compiles: no helper


@pytest.mark.parametrize(
    ("options", "cuda", "started"),
    [
        ({"device": "cpu", "preset": "default"}, True, True),
        ({"device": "auto", "preset": "default"}, False, True),
        ({"device": "auto", "preset": "default"}, True, False),  # solved on the GPU
        ({"device": "cuda", "preset": "default"}, True, False),
        ({"device": "cpu"}, False, False),  # no parameters: no Stage 2 (features)
    ],
)
def test_stage2_compiles_ahead_only_for_a_run_that_solves_it_on_the_cpu(
    options, cuda, started, monkeypatch
):
    import argparse

    from torchiid import cli

    monkeypatch.setattr("torch.cuda.is_available", lambda: cuda)

    class Ahead:
        starts = 0

        def start(self):
            self.starts += 1

    ahead = Ahead()
    cli._first_compilation(argparse.Namespace(quiet=True, **options), ahead)
    assert ahead.starts == int(started)


def test_commands_are_registered_in_one_table():
    names = [c.name for c in COMMANDS]
    assert len(set(names)) == len(names)
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert list(sub.choices) == names
    for command in COMMANDS:
        module = importlib.import_module(f"torchiid.commands.{command.module}")
        assert callable(module.add_arguments) and callable(module.run)


def _raise_from(cause):
    def fail(_directory):
        try:
            raise cause
        except BaseException as exc:
            # what numba's dispatcher raises when a Ctrl-C lands inside a compiled kernel
            raise SystemError("<numba dispatcher> returned a result with an exception set") from exc

    return fail


def test_ctrl_c_inside_a_compiled_kernel_is_reported_as_an_interruption(
    tmp_path, monkeypatch, capsys
):
    import torchiid.features.onnx_backend as onnx_backend

    monkeypatch.setattr(onnx_backend, "export_to_dir", _raise_from(KeyboardInterrupt()))
    assert main(["export-onnx", "-o", str(tmp_path)]) == 130
    err = capsys.readouterr().err
    assert "torchiid: interrupted" in err
    assert "internal error" not in err
    # the same wrapper around an ordinary failure is still an internal error: failed, status 1
    monkeypatch.setattr(onnx_backend, "export_to_dir", _raise_from(ValueError("bad")))
    assert main(["export-onnx", "-o", str(tmp_path)]) == 1
    assert "internal error (SystemError" in capsys.readouterr().err


# ----------------------------------------------------------------------------- memory limit


def test_the_memory_limit_variable_is_the_one_the_library_reads():
    from torchiid.commands.common import MEMORY_LIMIT_VARIABLE
    from torchiid.core import memory

    assert MEMORY_LIMIT_VARIABLE == memory.MEMORY_LIMIT_VARIABLE


def test_decompose_refuses_a_photo_over_the_memory_limit_and_restores_the_variable(
    photo, tmp_path, capsys, monkeypatch
):
    monkeypatch.delenv("TORCHIID_MEMORY_LIMIT", raising=False)
    out = tmp_path / "out"
    status = main(["decompose", str(photo / "cat.png"), "-o", str(out), "--memory-limit", "0.01"])
    err = capsys.readouterr().err
    assert status == 1
    assert "over the memory limit of 0.01 GB" in err and "--memory-limit" in err
    assert not out.exists()  # refused before any work: nothing written
    assert "TORCHIID_MEMORY_LIMIT" not in os.environ
    with pytest.raises(SystemExit) as stop:
        main(["decompose", str(photo / "cat.png"), "-o", str(out), "--memory-limit", "0"])
    assert stop.value.code == 2


# ----------------------------------------------------------------------------- exit


def _console(argv, code_before=""):
    code = f"import sys\n{code_before}\nfrom torchiid.cli import console_main\nconsole_main()\n"
    # Python's default buffering (a piped stdout holds its text until flushed)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    return subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=ROOT, env=env
    )


def test_the_console_script_is_console_main():
    text = (ROOT / "pyproject.toml").read_text()
    assert 'torchiid = "torchiid.cli:console_main"' in text


def test_the_console_script_keeps_the_status_and_every_line_it_printed(photo, tmp_path):
    out = tmp_path / "out"
    done = _console([*_argv("decompose", photo, out), *FAST])
    assert done.returncode == 0, done.stderr
    assert "1 done, 0 skipped, 0 failed" in done.stderr
    assert (out / "manifest.jsonl").read_text().count("\n") == 1  # written and closed
    missing = _console(["decompose", str(tmp_path / "no.png"), "-o", str(tmp_path / "o2")])
    assert missing.returncode == 1
    assert missing.stderr.endswith("torchiid: 1 of 1 input(s) failed\n")


def test_the_console_script_waits_for_child_processes(tmp_path):
    # a command that leaves a child running takes the ordinary exit, which joins it
    flag = tmp_path / "child-finished"
    before = f"""
import multiprocessing, time
import torchiid.cli as cli
def child():
    time.sleep(0.5)
    open({str(flag)!r}, "w").close()
def main(own_process=False):
    multiprocessing.get_context("spawn").Process(target=child).start()
    return 0
cli.main = main
"""
    code = f"{before}\nif __name__ == '__main__':\n    cli.console_main()\n"
    script = tmp_path / "script.py"
    script.write_text(code)
    # no pipes: a child holding them would make run() wait for it whatever the parent does
    done = subprocess.run(
        [sys.executable, str(script)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=ROOT,
        timeout=60,
    )
    assert done.returncode == 0
    assert flag.exists()  # the parent ended after its child, not before


def test_the_console_script_delivers_buffered_output_before_it_leaves():
    # a piped stdout is block-buffered: what a command printed must still arrive
    before = "import torchiid.cli as cli\ncli.main = lambda **kw: (print('a table row'), 3)[1]"
    done = _console([], before)
    assert done.returncode == 3
    assert done.stdout == "a table row\n"
