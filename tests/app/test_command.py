"""``torchiid app``: its options, its set-up errors, and that nothing else imports Gradio."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("gradio")

import torchiid.app as app  # noqa: E402
import torchiid.commands.app as command  # noqa: E402
from torchiid.cli import build_parser, main  # noqa: E402


def test_the_options_and_their_defaults():
    args = build_parser().parse_args(["app"])
    assert (args.host, args.port, args.share, args.device) == ("127.0.0.1", None, False, "auto")
    assert args.memory_limit is None and args.preset == "default"
    args = build_parser().parse_args(
        ["app", "--host", "0.0.0.0", "--port", "8080", "--share", "--memory-limit", "2.5"]
    )
    assert (args.host, args.port, args.share, args.memory_limit) == ("0.0.0.0", 8080, True, 2.5)


def test_help_names_every_option(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["app", "--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for option in ("--host", "--port", "--share", "--device", "--memory-limit", "--max-side"):
        assert option in text


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--preset", "nope"], "unknown preset 'nope'"),
        (["--iterations", "0"], "--iterations must be >= 1"),
    ],
)
def test_set_up_errors_end_in_one_line_before_serving(capsys, monkeypatch, argv, message):
    def no_serving(*args, **kwargs):  # pragma: no cover - must not be reached
        raise AssertionError("the server was started")

    monkeypatch.setattr(app, "serve", no_serving)
    assert main(["app", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("torchiid: error: ") and message in err and len(err.splitlines()) == 1


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--memory-limit", "-1"], "argument --memory-limit: must be a number of GB > 0"),
        (["--threads", "0"], "argument --threads: must be >= 1"),
    ],
)
def test_bad_run_options_are_usage_errors(capsys, monkeypatch, argv, message):
    def no_serving(*args, **kwargs):  # pragma: no cover - must not be reached
        raise AssertionError("the server was started")

    monkeypatch.setattr(app, "serve", no_serving)
    with pytest.raises(SystemExit) as stop:
        main(["app", *argv])
    assert stop.value.code == 2
    assert message in capsys.readouterr().err


def test_the_options_reach_the_server(monkeypatch, capsys):
    got = {}

    def serve(config, **kwargs):
        got.update(config=config, **kwargs)
        raise KeyboardInterrupt  # Ctrl-C: the server stops

    monkeypatch.setattr(app, "serve", serve)
    argv = [
        "app",
        "--port",
        "7999",
        "--memory-limit",
        "0.5",
        "--iterations",
        "2",
        "--device",
        "cpu",
    ]
    assert main([*argv, "--max-side", "256"]) == 0
    config = got["config"]
    assert (config.memory_limit, config.iterations, config.max_side) == (500_000_000, 2, 256)
    assert config.device == "cpu" and got["port"] == 7999 and got["share"] is False
    assert "torchiid app: stopped" in capsys.readouterr().err


def test_without_gradio_the_message_says_what_to_install(monkeypatch, capsys):
    monkeypatch.setattr(command, "gradio_installed", lambda: False)
    assert main(["app"]) == 2
    assert "pip install 'torchiid[app]'" in capsys.readouterr().err


def test_only_a_starting_server_imports_gradio():
    code = (
        "import sys, torchiid, torchiid.cli, torchiid.app; torchiid.cli.build_parser(); "
        "assert 'gradio' not in sys.modules, 'gradio imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
