"""Check the package's structure: import cycles, module length and function signatures.

Walks every module of ``torchiid/`` (or the folder given), reads its imports and definitions
with :mod:`ast` (nothing is imported or run) and prints a table of what exceeds the limits:

* import cycles between ``torchiid`` modules (imports inside ``if TYPE_CHECKING:`` blocks do
  not count: they never run);
* modules longer than ``--max-lines`` lines (default 450);
* functions and methods with more than ``--max-params`` parameters (default 12; ``self`` and
  ``cls`` do not count, ``*args`` and ``**kwargs`` do).

The last line sums it up; the exit status is 1 when anything exceeds a limit::

    python tools/check_structure.py
    python tools/check_structure.py --max-lines 450 --max-params 12 torchiid
"""

from __future__ import annotations

import argparse
import ast
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Report", "check_tree", "main"]


@dataclass(frozen=True)
class Report:
    """What :func:`check_tree` found.

    Attributes:
        cycles: each import cycle as the list of its modules, first module repeated last.
        long_modules: ``(path, lines)`` of every module over the line limit.
        long_signatures: ``(path:line, qualified name, parameters)`` over the parameter limit.
        modules: how many modules were read.
    """

    cycles: list[list[str]]
    long_modules: list[tuple[str, int]]
    long_signatures: list[tuple[str, str, int]]
    modules: int

    @property
    def clean(self) -> bool:
        """No cycle, no long module, no long signature."""
        return not (self.cycles or self.long_modules or self.long_signatures)


def _module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _runtime_imports(tree: ast.Module, module: str, is_package: bool) -> set[str]:
    """Absolute names of every module imported at run time (any depth, not TYPE_CHECKING)."""
    found: set[str] = set()
    package = module if is_package else module.rpartition(".")[0]

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def _signatures(tree: ast.Module, limit: int, where: str) -> list[tuple[str, str, int]]:
    over: list[tuple[str, str, int]] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                a = child.args
                names = [x.arg for x in [*a.posonlyargs, *a.args, *a.kwonlyargs]]
                count = len(names) + (a.vararg is not None) + (a.kwarg is not None)
                if names and names[0] in ("self", "cls"):
                    count -= 1
                name = f"{prefix}{child.name}"
                if count > limit:
                    over.append((f"{where}:{child.lineno}", name, count))
                visit(child, f"{name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(tree, "")
    return over


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module, as a closed path."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0

    def connect(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph[v]:
                component.sort()
                found.append([*component, component[0]])

    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def check_tree(root: Path, max_lines: int = 450, max_params: int = 12) -> Report:
    """Read every ``.py`` file below ``root`` (a package folder) and check the limits."""
    root = root.resolve()
    files = sorted(p for p in root.rglob("*.py") if "__pycache__" not in p.parts)
    names = {_module_name(root, p): p for p in files}
    graph: dict[str, set[str]] = {}
    long_modules: list[tuple[str, int]] = []
    long_signatures: list[tuple[str, str, int]] = []
    for name, path in names.items():
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text, filename=str(path))
        rel = str(path.relative_to(root.parent))
        lines = len(text.splitlines())
        if lines > max_lines:
            long_modules.append((rel, lines))
        long_signatures += _signatures(tree, max_params, rel)
        imported = _runtime_imports(tree, name, path.name == "__init__.py")
        # a package's module imports its package's __init__ first: that edge is implied,
        # not a cycle of the code's making, so only module-to-module imports count
        graph[name] = {m for m in imported if m in names and m != name}
        graph[name] -= {p for p in graph[name] if name.startswith(p + ".")}
    return Report(_cycles(graph), long_modules, long_signatures, len(names))


def main(argv: list[str] | None = None) -> int:
    """Print the table; exit status 1 when a limit is exceeded."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", type=Path, default=Path(__file__).parents[1] / "torchiid")
    ap.add_argument("--max-lines", type=int, default=450, help="longest module (lines)")
    ap.add_argument("--max-params", type=int, default=12, help="most parameters of a function")
    args = ap.parse_args(argv)
    report = check_tree(args.root, args.max_lines, args.max_params)
    rows = [
        ("import cycles", report.cycles, "; ".join(" -> ".join(c) for c in report.cycles)),
        (
            f"modules over {args.max_lines} lines",
            report.long_modules,
            ", ".join(f"{p} ({n})" for p, n in sorted(report.long_modules, key=lambda x: -x[1])),
        ),
        (
            f"functions over {args.max_params} parameters",
            report.long_signatures,
            ", ".join(f"{q} ({n}, {w})" for w, q, n in report.long_signatures),
        ),
    ]
    print("| check | found | details |")
    print("| --- | --- | --- |")
    for label, found, details in rows:
        print(f"| {label} | {len(found)} | {details} |")
    state = "clean" if report.clean else "limits exceeded"
    print(f"\n{report.modules} modules read: {state}")
    return 0 if report.clean else 1


if __name__ == "__main__":
    raise SystemExit(main())
