"""MkDocs hook: the Parameters reference, generated from the dataclass itself.

``docs/reference/parameters.md`` holds the marker ``<!-- parameters-reference -->``; this hook
replaces it with one table per group of :class:`torchiid.params.Parameters` and a table of each
preset's differences from the default. A field whose type is itself a dataclass is a group and
is walked recursively; every other field is a row: its name, type and default, and from the field's
``metadata`` the keys ``"doc"`` (meaning), ``"paper"`` (the paper's value; ``None`` where the
paper has none), ``"valid"`` (the valid range, as text) and ``"why"`` (why the default differs
from the paper's value). A field without metadata falls back on the class docstring's entry for
it (its section gives the group, a ``(paper: …)`` remark the paper's value).

Configured in ``mkdocs.yml`` under ``hooks:``; ``tests/test_docs.py`` builds the site.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import typing
from typing import Any

MARKER = "<!-- parameters-reference -->"
PAGE = "reference/parameters.md"


def _markdown(text: str) -> str:
    """The reStructuredText roles and literals of a docstring as Markdown, one line, table-safe."""
    text = re.sub(r":(?:func|class|meth|mod|data|attr):`~?([\w.]+)`", _last_part, text)
    text = text.replace("``", "`")
    # outside code spans, < and > are text (`1 - <g_i, g_j>`), not HTML tags
    parts = text.split("`")
    parts[::2] = [p.replace("<", "&lt;").replace(">", "&gt;") for p in parts[::2]]
    return " ".join("`".join(parts).split()).replace("|", "\\|")


def _last_part(match: re.Match[str]) -> str:
    return f"`{match.group(1).rsplit('.', 1)[-1]}`"


def _docstring_entries(cls: type) -> dict[str, tuple[str, str]]:
    """``{field: (section, text)}`` from a Google-style class docstring.

    A section is a line ending in ``:`` at the first indentation; an entry is ``name: text`` one
    level deeper, with its continuation lines. A paragraph that names fields inline (``a, b, c
    turn ... on or off``) gives every field it names that paragraph's text.
    """
    doc = inspect.getdoc(cls) or ""
    entries: dict[str, tuple[str, str]] = {}
    section, current, paragraph = "", None, []
    names = {f.name for f in dataclasses.fields(cls)}

    def close_paragraph() -> None:
        text = " ".join(paragraph)
        head, _, rest = text.partition(":")
        for name in re.findall(r"\b\w+\b", text):
            if name in names and name not in entries and rest:
                entries[name] = (head.strip(), rest.strip())
        paragraph.clear()

    for line in doc.splitlines():
        indent = len(line) - len(line.lstrip())
        stripped = line.strip()
        if not stripped:
            close_paragraph()
            current = None
            continue
        match = re.match(r"(\w+):\s*(.*)", stripped)
        if indent == 0 and stripped.endswith(":"):
            close_paragraph()
            section, current = stripped[:-1], None
        elif indent > 0 and match and match.group(1) in names and indent <= 4:
            current = match.group(1)
            entries[current] = (section, match.group(2))
        elif current is not None and indent > 4:
            sec, text = entries[current]
            entries[current] = (sec, f"{text} {stripped}")
        elif indent == 0:
            paragraph.append(stripped)
    close_paragraph()
    return entries


def _paper_from_text(text: str) -> str | None:
    match = re.search(r"\(paper[^:)]*:\s*([^;)]+)", text)
    return match.group(1).strip() if match else None


def _value(value: Any) -> str:
    if value is dataclasses.MISSING:
        return "required"
    return f"`{value!r}`"


def _leaves(cls: type, group: str = "") -> list[dict[str, Any]]:
    """Every leaf field of ``cls`` (recursing into dataclass-typed fields), with its details."""
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # unresolvable annotations: show them as written
        hints = {}
    entries = _docstring_entries(cls)
    rows: list[dict[str, Any]] = []
    for field in dataclasses.fields(cls):
        kind = hints.get(field.name, field.type)
        if dataclasses.is_dataclass(kind):
            rows += _leaves(kind, field.name)
            continue
        section, text = entries.get(field.name, ("", ""))
        meta = dict(field.metadata)
        if field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            default = dataclasses.MISSING
        paper = meta["paper"] if "paper" in meta else _paper_from_text(text)
        rows.append(
            {
                "group": group or section or "Other",
                "name": field.name,
                "type": kind if isinstance(kind, str) else getattr(kind, "__name__", str(kind)),
                "default": default,
                "doc": meta.get("doc", text),
                "paper": "none" if "paper" in meta and paper is None else paper,
                "valid": meta.get("valid"),
                "why": meta.get("why"),
            }
        )
    return rows


def reference() -> str:
    """The Markdown of the reference: one table per group, then the presets."""
    from torchiid.params import PRESETS, Parameters

    rows = _leaves(Parameters)
    out: list[str] = []
    groups: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(row["group"], []).append(row)
    for group, members in groups.items():
        out += [f"### {_markdown(group)}", ""]
        out += [
            "| field | type | default | paper | valid | meaning |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for row in members:
            meaning = _markdown(row["doc"]) or "—"
            if row["why"]:
                meaning += f" *Why not the paper's value:* {_markdown(row['why'])}"
            paper = row["paper"]
            paper_text = "—" if paper is None else _markdown(str(paper))
            valid = _markdown(str(row["valid"])) if row["valid"] else "—"
            out.append(
                f"| `{row['name']}` | `{_markdown(row['type'])}` | {_value(row['default'])} "
                f"| {paper_text} | {valid} | {meaning} |"
            )
        out.append("")
    defaults = {row["name"]: row["default"] for row in rows}
    out += ["### Presets", "", "Each preset's differences from `default` (`Parameters()`):", ""]
    out += ["| preset | field | value | default |", "| --- | --- | --- | --- |"]
    for name, changes in PRESETS.items():
        if not changes:
            out.append(f"| `{name}` | — | — | — |")
        for key, value in changes.items():
            default = _value(defaults.get(key, dataclasses.MISSING))
            out.append(f"| `{name}` | `{key}` | {_value(value)} | {default} |")
    out.append("")
    return "\n".join(out)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Replace the marker of the Parameters page by the generated reference."""
    if page.file.src_uri != PAGE:
        return markdown
    if MARKER not in markdown:
        raise ValueError(f"{PAGE} lost its marker {MARKER}")
    return markdown.replace(MARKER, reference())
