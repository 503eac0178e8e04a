import importlib
import sys

import pytest

from torchiid.core.exceptions import (
    ImageError,
    ParameterError,
    ShapeError,
    TorchiidError,
    caused_by_interrupt,
    describe_error,
    one_line,
    unimportable_dependency,
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


def _import_error(name: str) -> ImportError:
    try:
        importlib.import_module(name)
    except ImportError as err:
        return err
    raise AssertionError(f"{name} imported")


def test_a_library_that_cannot_be_imported_is_named_with_its_fix(tmp_path, monkeypatch):
    broken = tmp_path / "brokenlib"
    broken.mkdir()
    (broken / "__init__.py").write_text("from brokenlib import _core\n")
    (broken / "_core.py").write_text(
        'raise ImportError("libbroken.so: cannot open shared object")\n'
    )
    (tmp_path / "outerlib.py").write_text("import brokenlib\n")  # as kornia imports torch
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("brokenlib", "outerlib"):
        err = _import_error(name)
        assert unimportable_dependency(err) == (
            "brokenlib is installed but cannot be imported (libbroken.so: cannot open shared "
            "object); reinstall it: pip install --force-reinstall --no-deps brokenlib"
        )
        assert describe_error(err) == unimportable_dependency(err)  # a failed input says so
        for module in ("brokenlib", "brokenlib._core", "outerlib"):
            sys.modules.pop(module, None)
    missing = _import_error("torchiid_test_not_installed")
    assert unimportable_dependency(missing) == (
        "torchiid_test_not_installed is not installed (No module named "
        "'torchiid_test_not_installed'); install it: pip install torchiid_test_not_installed"
    )
    # a module whose pip name differs, where the installed metadata cannot say it
    with pytest.raises(ModuleNotFoundError) as raised:
        exec(
            "raise ModuleNotFoundError(\"No module named 'OpenEXR'\", name='OpenEXR')",
            {"__name__": "torchiid.io.exr"},
        )
    assert unimportable_dependency(raised.value) == (
        "OpenEXR is not installed (No module named 'OpenEXR'); install it: pip install openexr"
    )
    # the same, imported from a module of torchiid's
    with pytest.raises(ImportError) as raised:
        exec("import torchiid_test_not_installed", {"__name__": "torchiid.some_module"})
    assert unimportable_dependency(raised.value) == unimportable_dependency(missing)


def test_an_import_error_of_torchiid_itself_or_another_error_is_not_the_installations(
    tmp_path, monkeypatch
):
    assert unimportable_dependency(_import_error("torchiid.no_such_module")) is None
    assert unimportable_dependency(_import_error("json.no_such_module")) is None  # Python's own
    # a library that imported fine raises ImportError as it runs, or imports what is missing
    (tmp_path / "loadedlib.py").write_text(
        "def feature():\n    raise ImportError('feature needs a newer GPU driver')\n"
        "def optional():\n    import torchiid_test_optional_dep\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    loadedlib = importlib.import_module("loadedlib")
    try:
        with pytest.raises(ImportError) as raised:
            loadedlib.feature()
        assert unimportable_dependency(raised.value) is None
        with pytest.raises(ImportError) as raised:
            loadedlib.optional()
        assert unimportable_dependency(raised.value) == (
            "torchiid_test_optional_dep is not installed (No module named "
            "'torchiid_test_optional_dep'); install it: pip install torchiid_test_optional_dep"
        )
    finally:
        sys.modules.pop("loadedlib", None)
    assert unimportable_dependency(KeyError("x")) is None
    bug = describe_error(_import_error("torchiid.no_such_module"))
    assert bug.startswith("internal error (ModuleNotFoundError") and "--verbose" in bug
