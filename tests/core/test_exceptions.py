import pytest

from torchiid.core.exceptions import (
    ImageError,
    ParameterError,
    ShapeError,
    TorchiidError,
    caused_by_interrupt,
    describe_error,
    one_line,
)


@pytest.mark.parametrize("cls", [ImageError, ShapeError, ParameterError])
def test_user_errors_are_torchiid_and_value_errors(cls):
    assert issubclass(cls, TorchiidError) and issubclass(cls, ValueError)


def test_descriptions_are_one_line_and_say_what_kind_of_error():
    assert one_line("a\n  b\tc ") == "a b c"
    assert describe_error(ShapeError("expected\n(B, 3, H, W)")) == "expected (B, 3, H, W)"
    missing = FileNotFoundError(2, "No such file or directory", "photo.png")
    assert describe_error(missing) == "cannot access photo.png (No such file or directory)"
    assert describe_error(MemoryError("out")) == "MemoryError: out"
    bug = describe_error(KeyError("x"))
    assert bug.startswith("internal error (KeyError") and "--verbose" in bug


def test_an_interrupt_anywhere_in_the_cause_chain_is_found():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise SystemError("returned a result with an exception set") from inner
    except SystemError as outer:
        assert caused_by_interrupt(outer)
    loop = RuntimeError("a")
    loop.__context__ = RuntimeError("b")
    loop.__context__.__context__ = loop  # a cycle ends the walk
    assert not caused_by_interrupt(loop)
