"""The import structure of the package: no import cycles, no private names across modules.

Every module of ``torchiid`` is parsed (not executed) with :mod:`ast`, and every import of a
``torchiid`` module is collected, at module level or inside a function (lazy imports count: a
cycle closed only by a lazy import still ties the modules together and breaks as soon as the
import is moved to the top).

How an import becomes edges of the module graph (``importer -> target``):

* ``import torchiid.a.b`` and ``from torchiid.a.b import name``: the target is ``torchiid.a.b``.
* ``from torchiid.a import b``: the target is ``torchiid.a.b`` when that is a module, else the
  package ``torchiid.a`` (``b`` is then a name defined in, or re-exported by, its ``__init__``).
* A package is its ``__init__``: importing ``torchiid.a`` depends on ``torchiid/a/__init__.py``.
* Importing ``torchiid.a.b`` runs the ``__init__`` of every package above it first, so it also
  depends on those packages, except the ones the importer itself lies in: they are already being
  imported when the importer runs. Hence a package ``__init__`` that imports (re-exports) its own
  submodules is not a cycle by itself, while a submodule that imports its parent package
  explicitly (``from torchiid.a import name`` in ``torchiid/a/x.py``) while that ``__init__``
  imports the submodule is one. Likewise ``torchiid.x.m`` importing ``torchiid.y.n`` depends on
  ``torchiid/y/__init__.py`` and everything it re-exports. The root ``torchiid/__init__.py`` is
  above every module, so it may re-export anything; an explicit ``import torchiid`` or
  ``from torchiid import name`` inside the package is an edge to it like any other.

No exceptions are allowed: the expected set of cycles is empty.
"""

from __future__ import annotations

import ast
import importlib.util
import pkgutil
from dataclasses import dataclass
from pathlib import Path

import torchiid

PACKAGE = "torchiid"

ALLOWED_CYCLES: list[tuple[str, ...]] = []  # NONE: the test is strict
ALLOWED_PRIVATE_IMPORTS: list[tuple[str, str, str]] = []  # NONE


@dataclass(frozen=True)
class ImportSite:
    """One ``import`` statement of a ``torchiid`` module."""

    importer: str
    path: Path
    line: int
    lazy: bool
    statement: str

    def where(self) -> str:
        kind = "lazy import" if self.lazy else "module-level import"
        return f"{self.path}:{self.line} ({kind}): {self.statement}"


def _modules() -> dict[str, tuple[Path, bool]]:
    """Every module of the package: name -> (source file, is a package)."""

    def fail(name: str) -> None:
        raise ImportError(f"pkgutil.walk_packages could not import {name}")

    found = {PACKAGE: (Path(torchiid.__file__), True)}
    for info in pkgutil.walk_packages(torchiid.__path__, prefix=PACKAGE + ".", onerror=fail):
        spec = importlib.util.find_spec(info.name)
        assert spec is not None and spec.origin is not None, info.name
        found[info.name] = (Path(spec.origin), info.ispkg)
    return found


MODULES = _modules()


def _package_of(module: str) -> str:
    """The package a module's relative imports start from."""
    return module if MODULES[module][1] else module.rpartition(".")[0]


def _absolute(module: str, node: ast.ImportFrom) -> str | None:
    """The absolute module name of a ``from ... import`` (``None``: outside any package)."""
    if node.level == 0:
        return node.module
    base = _package_of(module).split(".")
    if node.level - 1 >= len(base):
        return None
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_ours(name: str | None) -> bool:
    return name is not None and (name == PACKAGE or name.startswith(PACKAGE + "."))


def _existing(name: str) -> str:
    """``name`` or, when it is no module, the longest module prefix (the defining module)."""
    while name not in MODULES and "." in name:
        name = name.rpartition(".")[0]
    return name


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _function_scoped_nodes(tree: ast.Module) -> set[int]:
    """``id`` of every node inside a function body (lazy imports)."""
    inside: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            inside.update(id(child) for child in ast.walk(node) if child is not node)
    return inside


def _imports() -> tuple[dict[str, dict[str, list[ImportSite]]], list[tuple[ImportSite, str]]]:
    """The module graph (importer -> target -> sites) and the private names imported."""
    root = Path(torchiid.__file__).parent.parent
    graph: dict[str, dict[str, list[ImportSite]]] = {m: {} for m in MODULES}
    private: list[tuple[ImportSite, str]] = []
    for module, (path, _) in MODULES.items():
        source = path.read_text(encoding="utf-8")
        tree = ast.parse(source, filename=str(path))
        lazy_nodes = _function_scoped_nodes(tree)
        for node in ast.walk(tree):
            if not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            site = ImportSite(
                module,
                path.relative_to(root),
                node.lineno,
                id(node) in lazy_nodes,
                " ".join((ast.get_source_segment(source, node) or "").split()),
            )
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [_existing(a.name) for a in node.names if _is_ours(a.name)]
                for alias in node.names:
                    private_parts = [p for p in alias.name.split(".") if _is_private(p)]
                    if _is_ours(alias.name) and private_parts:
                        private.append((site, private_parts[0]))
            else:
                base = _absolute(module, node)
                if not _is_ours(base):
                    continue
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    source_module = sub if sub in MODULES else _existing(base)
                    targets.append(source_module)
                    allowed = (module, source_module, alias.name) in ALLOWED_PRIVATE_IMPORTS
                    if _is_private(alias.name) and not allowed:
                        private.append((site, alias.name))
            for target in targets:
                for dep in _with_parent_packages(module, target):
                    sites = graph[module].setdefault(dep, [])
                    if site not in sites:
                        sites.append(site)
    return graph, private


def _with_parent_packages(importer: str, target: str) -> list[str]:
    """``target`` and the packages above it that importing it runs (see the module notes)."""
    deps = [target]
    parts = target.split(".")
    for i in range(1, len(parts)):
        parent = ".".join(parts[:i])
        if importer == parent or importer.startswith(parent + "."):
            continue  # the importer lies in this package: it is already imported
        deps.append(parent)
    return deps


def _strongly_connected(graph: dict[str, dict[str, list[ImportSite]]]) -> list[list[str]]:
    """Tarjan's strongly connected components (iterative), in a stable order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        top = stack.pop()
                        on_stack.discard(top)
                        component.append(top)
                        if top == node:
                            break
                    if len(component) > 1 or node in graph[node]:
                        components.append(sorted(component))
    return sorted(components)


def _cycle_in(component: list[str], graph: dict[str, dict[str, list[ImportSite]]]) -> list[str]:
    """A shortest cycle through the component's first module, as a path ``[a, ..., a]``."""
    start = component[0]
    members = set(component)
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(graph[node]):
                if child not in members:
                    continue
                if child == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [start, *reversed(path[:-1]), start] if node != start else [start] * 2
                if child not in previous:
                    previous[child] = node
                    following.append(child)
        frontier = following
    raise AssertionError(f"no cycle found in the component {component}")  # pragma: no cover


def _describe(cycle: list[str], graph: dict[str, dict[str, list[ImportSite]]]) -> str:
    lines = ["  " + " -> ".join(cycle)]
    for a, b in zip(cycle, cycle[1:], strict=False):
        lines.append(f"    {a} -> {b}:")
        lines.extend(f"      {site.where()}" for site in graph[a][b])
    return "\n".join(lines)


GRAPH, PRIVATE = _imports()


def test_every_module_is_parsed():
    assert "torchiid.cli" in MODULES and "torchiid.features.proposals" in MODULES
    assert all(path.suffix == ".py" for path, _ in MODULES.values())


def test_no_import_cycles():
    cycles = []
    for component in _strongly_connected(GRAPH):
        cycle = _cycle_in(component, GRAPH)
        if tuple(cycle) in ALLOWED_CYCLES:
            continue
        cycles.append(
            f"modules in one cycle: {', '.join(component)}\n"
            f"  for example:\n{_describe(cycle, GRAPH)}"
        )
    assert not cycles, f"{len(cycles)} import cycle(s):\n" + "\n".join(cycles)


def test_no_private_names_imported_across_modules():
    found = [f"{site.where()}  [imports {name}]" for site, name in PRIVATE]
    assert not found, "private names imported from other modules:\n" + "\n".join(found)


# --- the checker itself, on hand-made graphs ---------------------------------------------------


def _graph(edges: dict[str, list[str]]) -> dict[str, dict[str, list[ImportSite]]]:
    nodes = set(edges) | {b for bs in edges.values() for b in bs}
    site = ImportSite("x", Path("x.py"), 1, False, "import x")
    return {n: {b: [site] for b in edges.get(n, [])} for n in nodes}


def test_checker_finds_cycles_and_their_paths():
    g = _graph({"a": ["b"], "b": ["c"], "c": ["a", "d"], "d": [], "e": ["e"]})
    comps = _strongly_connected(g)
    assert comps == [["a", "b", "c"], ["e"]]
    assert _cycle_in(comps[0], g) == ["a", "b", "c", "a"]
    assert _cycle_in(comps[1], g) == ["e", "e"]
    assert _strongly_connected(_graph({"a": ["b"], "b": ["c"]})) == []


def test_parent_packages_count_only_from_outside():
    assert _with_parent_packages("torchiid.priors.x", "torchiid.features.segmentation") == [
        "torchiid.features.segmentation",
        "torchiid.features",
    ]
    assert _with_parent_packages("torchiid.features", "torchiid.features.semantic") == [
        "torchiid.features.semantic"
    ]
    assert _with_parent_packages("torchiid.features.semantic", "torchiid.features.patches") == [
        "torchiid.features.patches"
    ]
