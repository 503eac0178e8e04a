"""tools/check_structure.py: cycles, long modules and long signatures found from the source."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tool(load_tool):
    return load_tool("check_structure")


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "pkg"
    for name, text in {"__init__.py": "", **files}.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_cycle_found_through_relative_and_absolute_imports(tool, tmp_path):
    root = _package(
        tmp_path,
        {
            "a.py": "from pkg.b import f\n",
            "sub/__init__.py": "",
            "b.py": "def f():\n    from .sub import c\n",
            "sub/c.py": "from .. import a\n",
            "d.py": "import pkg.a\n",
        },
    )
    report = tool.check_tree(root)
    assert report.cycles == [["pkg.a", "pkg.b", "pkg.sub.c", "pkg.a"]]
    assert not report.clean


def test_type_checking_imports_are_not_cycles(tool, tmp_path):
    root = _package(
        tmp_path,
        {
            "a.py": (
                "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.b import X\n"
            ),
            "b.py": "from pkg.a import Y\n",
        },
    )
    assert tool.check_tree(root).cycles == []


def test_imports_of_a_parent_package_are_not_cycles(tool, tmp_path):
    # importing pkg.a runs pkg/__init__ first anyway: an edge back to a parent is implied
    root = _package(tmp_path, {"__init__.py": "from pkg.a import f\n", "a.py": "import pkg\n"})
    assert tool.check_tree(root).cycles == []
    root = _package(
        tmp_path / "2",
        {
            "__init__.py": "from pkg.a import f\n",
            "a.py": "import pkg.b\n",
            "b.py": "from pkg import a\n",
        },
    )
    assert tool.check_tree(root).cycles == [["pkg.a", "pkg.b", "pkg.a"]]


def test_long_modules_and_signatures(tool, tmp_path):
    args13 = ", ".join(f"a{i}" for i in range(13))
    args12 = ", ".join(f"a{i}" for i in range(11))
    root = _package(
        tmp_path,
        {
            "long.py": "x = 1\n" * 451,
            "short.py": "x = 1\n" * 450,
            "sig.py": (
                f"def big({args13}):\n    pass\n"
                f"class K:\n    def method(self, {args12}, *rest):\n        pass\n"
                f"    def star(self, {args12}, *rest, **more):\n        pass\n"
            ),
        },
    )
    report = tool.check_tree(root, max_lines=450, max_params=12)
    assert report.long_modules == [("pkg/long.py", 451)]
    assert [(name, n) for _, name, n in report.long_signatures] == [("big", 13), ("K.star", 13)]


def test_main_prints_a_table_and_exit_status(tool, tmp_path, capsys):
    root = _package(tmp_path, {"a.py": "x = 1\n"})
    assert tool.main([str(root)]) == 0
    out = capsys.readouterr().out
    assert "| import cycles | 0 |" in out and "clean" in out
    root = _package(tmp_path / "2", {"a.py": "x = 1\n" * 20})
    assert tool.main([str(root), "--max-lines", "10"]) == 1


def test_the_package_has_no_cycles_long_modules_or_long_signatures(tool):
    report = tool.check_tree(ROOT / "torchiid")
    assert report.modules > 100
    assert report.cycles == []
    assert report.long_modules == []
    assert report.long_signatures == []
