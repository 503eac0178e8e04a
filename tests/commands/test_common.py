import argparse

import pytest

from torchiid.commands.common import run_options


def _parser():
    return argparse.ArgumentParser(prog="torchiid", parents=[run_options()])


def test_run_options_read_whole_threads_and_fractional_gigabytes():
    args = _parser().parse_args(["--threads", "3", "--memory-limit", "1.5"])
    assert args.threads == 3 and isinstance(args.threads, int)
    assert args.memory_limit == 1.5 and isinstance(args.memory_limit, float)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--threads", "two"], "argument --threads: not a whole number: 'two'"),
        (["--threads", "1.5"], "argument --threads: not a whole number: '1.5'"),
        (["--threads", "0"], "argument --threads: must be >= 1, got 0"),
        (["--memory-limit", "lots"], "argument --memory-limit: not a number of GB: 'lots'"),
        (["--memory-limit", "inf"], "argument --memory-limit: must be a number of GB > 0, got inf"),
    ],
)
def test_run_options_name_what_is_wrong_with_a_number(capsys, argv, message):
    with pytest.raises(SystemExit) as stop:
        _parser().parse_args(argv)
    assert stop.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--iterations", "0", "torchiid: error: --iterations must be >= 1, got 0"),
        ("--max-side", "-5", "torchiid: error: --max-side must be >= 0 (0: the full resolution), "
         "got -5"),
    ],
)  # fmt: skip
def test_the_method_options_are_named_as_typed(tmp_path, capsys, option, value, message):
    from torchiid.cli import main

    argv = ["decompose", str(tmp_path / "any.png"), "-o", str(tmp_path / "out"), option, value]
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == message
    assert not (tmp_path / "out").exists()
