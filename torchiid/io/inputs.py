"""Turning the files, folders, globs and list files a user names into the images to process.

Every image gets an output **key**: its path, without the suffix, relative to the root it was
found under, with ``/`` between folders. ``torchiid decompose`` writes the image's files as
``OUT/<key>-reflectance.png`` etc., so the folder structure below each root is kept and two
``IMG_0001.jpg`` in different folders never write the same files. The roots:

* a **file** named on its own: its own folder (key = the file's stem);
* a **folder**: the folder (its image files but hidden ones; with ``recursive``, those of its
  subfolders too, hidden folders excepted, symbolic links to folders not followed);
* a **glob** (``photos/*/*.jpg``, ``photos/**/*.png``; ``**`` matches any depth): the folder
  before its first wildcard; image files only (none from the output folder below it);
* a **list file** (:func:`read_list_file`): the deepest folder holding every image it lists.
"""

from __future__ import annotations

import csv
import glob
import os
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from torchiid.core.exceptions import TorchiidError

__all__ = [
    "IMAGE_SUFFIXES",
    "InputItem",
    "collect_inputs",
    "file_identity",
    "list_inputs",
    "read_list_file",
    "unique_keys",
    "walks_into",
]

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr", ".npy"}
"""File suffixes (lower case) taken from a folder or a glob by :func:`collect_inputs`."""

_MAGIC = set("*?[")


class KeyParts:
    """The :attr:`stem` and :attr:`folder` of an output ``key``, for the classes that hold one."""

    key: str

    @property
    def stem(self) -> str:
        """The last part of the key: the prefix of the image's output file names."""
        return self.key.rpartition("/")[2]

    @property
    def folder(self) -> str:
        """The folder part of the key (``""`` for the output folder itself)."""
        return self.key.rpartition("/")[0]


@dataclass(frozen=True)
class InputItem(KeyParts):
    """One image to process.

    Attributes:
        path: the image file, as named (relative paths stay relative to the working folder).
        key: where its outputs go, relative to the output folder, without the ``-layer.ext``
            part: ``"photo"`` or ``"2019/summer/IMG_0001"`` (``/``-separated).
        mask: a mask file for this image only (a list file's ``mask`` column), or ``None``.
    """

    path: Path
    key: str
    mask: Path | None = None


def _is_image(name: str) -> bool:
    return os.path.splitext(name)[1].lower() in IMAGE_SUFFIXES


def _key(path: Path, root: Path) -> str:
    rel = os.path.relpath(path, root) if str(root) not in ("", ".") else os.fspath(path)
    rel = os.path.splitext(rel)[0]
    return "/".join(part for part in Path(rel).parts if part not in ("", "."))


def _same_folder(a: os.DirEntry, excluded: set[tuple[int, int]]) -> bool:
    try:
        st = a.stat(follow_symlinks=False)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) in excluded


def _walk(
    folder: Path,
    recursive: bool,
    excluded: set[tuple[int, int]],
    skip: Collection[str] = frozenset(),
) -> Iterable[Path]:
    """Image files of ``folder`` (sorted by name), then those of its subfolders (if recursive).

    Files whose absolute path is in ``skip`` are left out.
    """
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError as exc:
        raise TorchiidError(f"{folder}: cannot list the folder ({exc.strerror or exc})") from None
    subfolders = []
    real = file_identity(folder) if skip else ""  # resolved once: each file joins it
    for entry in entries:
        try:
            if entry.is_file():
                # hidden files (macOS's ._IMG.jpg resource forks, editors' backups) are not
                # photos of the folder; a hidden file named on its own is still taken
                if _is_image(entry.name) and not entry.name.startswith("."):
                    path = Path(folder, entry.name)
                    if not skip or _identity(entry, real) not in skip:
                        yield path
            elif recursive and entry.is_dir(follow_symlinks=False):
                if not entry.name.startswith(".") and not _same_folder(entry, excluded):
                    subfolders.append(Path(folder, entry.name))
        except OSError:
            continue
    for sub in subfolders:
        yield from _walk(sub, recursive, excluded, skip)


def _glob_root(pattern: str) -> Path:
    parts = Path(pattern).parts
    literal = []
    for part in parts:
        if _MAGIC & set(part):
            break
        literal.append(part)
    return Path(*literal) if literal else Path(".")


def _below_excluded(
    path: Path, root: Path, excluded: set[tuple[int, int]] | None, seen: dict[str, bool]
) -> bool:
    """``path`` lies in an excluded folder below ``root`` (its folders stat-ed once each)."""
    if not excluded:
        return False
    rel = Path(os.path.relpath(path, root)) if str(root) not in ("", ".") else path
    folder = root
    for part in rel.parts[:-1]:
        folder = folder / part
        name = os.fspath(folder)
        if name not in seen:
            try:
                st = os.stat(folder)
                seen[name] = (st.st_dev, st.st_ino) in excluded
            except OSError:
                seen[name] = False
        if seen[name]:
            return True
    return False


def _expand_glob(
    pattern: str,
    excluded: set[tuple[int, int]] | None = None,
    skip: Collection[str] = frozenset(),
) -> list[InputItem]:
    root = _glob_root(pattern)
    seen: dict[str, bool] = {}
    found = sorted(
        Path(p)
        for p in glob.glob(pattern, recursive=True)
        if _is_image(p)
        and os.path.isfile(p)
        and not (skip and file_identity(p) in skip)
        and not _below_excluded(Path(p), root, excluded, seen)
    )
    if not found:
        raise TorchiidError(f"{pattern}: no image file matches this pattern")
    return [InputItem(p, _key(p, root)) for p in found]


def read_list_file(path: Path) -> list[InputItem]:
    """The images a list file names.

    A ``.csv`` file has a header line with a ``path`` column and optionally a ``mask`` column
    (a mask file for that image; empty for none); any other file has one path per line (blank
    lines and lines starting with ``#`` are skipped). Relative paths are relative to the list
    file's folder. The keys are the paths relative to the deepest folder holding every listed
    image, so a flat list keeps plain names and a list over a tree keeps its structure.

    Raises:
        TorchiidError: the list file is missing or unreadable, a CSV file has no ``path``
            column or an empty path, or the list names no image.
    """
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise TorchiidError(f"{path}: no such list file") from None
    except IsADirectoryError:
        raise TorchiidError(f"{path}: is a directory, not a list file") from None
    except UnicodeDecodeError as exc:
        raise TorchiidError(
            f"{path}: not a UTF-8 text file (byte {exc.object[exc.start]:#04x} at {exc.start})"
        ) from None
    except OSError as exc:
        raise TorchiidError(f"{path}: cannot read the list file ({exc.strerror or exc})") from None
    base = path.parent
    rows: list[tuple[str, str]] = []
    if path.suffix.lower() == ".csv":
        reader = csv.DictReader(text.splitlines())
        columns = {(c or "").strip().lower(): c for c in reader.fieldnames or []}
        if "path" not in columns:
            found = ", ".join(repr(c) for c in reader.fieldnames or []) or "none"
            raise TorchiidError(f"{path}: a CSV list needs a 'path' column (columns: {found})")
        for row in reader:
            image = (row.get(columns["path"]) or "").strip()
            mask = (row.get(columns["mask"]) or "").strip() if "mask" in columns else ""
            if not image:
                raise TorchiidError(f"{path}: line {reader.line_num}: empty path")
            rows.append((image, mask))
    else:
        for line in text.splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                rows.append((line, ""))
    if not rows:
        raise TorchiidError(f"{path}: the list names no image")
    images = [
        (base / Path(p).expanduser(), base / Path(m).expanduser() if m else None) for p, m in rows
    ]
    folders = {os.path.abspath(p.parent) for p, _ in images}
    try:
        root = Path(os.path.commonpath(sorted(folders)))
    except ValueError:  # paths on different drives: keep only the names
        root = None
    items = []
    for image, mask in images:
        key = _key(Path(os.path.abspath(image)), root) if root is not None else image.stem
        items.append(InputItem(Path(os.path.normpath(image)), key, mask))
    return items


def list_inputs(
    inputs: Sequence[Path | str],
    *,
    recursive: bool = False,
    lists: Sequence[Path] = (),
    exclude: Sequence[Path] = (),
    skip: Collection[str] = frozenset(),
) -> list[InputItem]:
    """Every image named by files, folders, globs and list files, with its output key.

    Args:
        inputs: files, folders and glob patterns (a name that exists is never taken as a
            pattern). A file is taken as it is, whatever its suffix.
        recursive: also take the images in the folders' subfolders.
        lists: list files (see :func:`read_list_file`), read after ``inputs``.
        exclude: folders whose images are never taken from a folder walk or a glob (the output
            folder, when it lies below an input folder or a glob's fixed part, so that outputs
            are not taken as inputs). Files named on their own or in a list file are always
            taken, and so are the images of a folder, or a glob's fixed part, that is itself
            excluded.
        skip: files never taken from a folder walk or a glob, as :func:`file_identity` names
            them: the outputs that the output folder's manifest records
            (:meth:`~torchiid.collection.manifest.Manifest.written_files`), for an output
            folder that is also an input folder. Files named on their own are still taken.

    Returns:
        The images in the order given, each folder's and glob's images sorted by path.
        Repeats of the same file are kept (see :func:`unique_keys`).

    Raises:
        TorchiidError: a folder holds no image, a glob matches no image, or a list file
            cannot be used.
    """
    excluded = set()
    for folder in exclude:
        try:
            st = os.stat(folder)
            excluded.add((st.st_dev, st.st_ino))
        except OSError:
            pass
    out: list[InputItem] = []
    for name in inputs:
        p = Path(name)
        if p.is_dir():
            found = list(_walk(p, recursive, excluded, skip))
            if not found:
                where = " or its subfolders" if recursive else ""
                hint = ""
                if not recursive and any(_walk(p, True, excluded, skip)):
                    hint = "; its subfolders do: -r (recursive=True in Python) takes them"
                raise TorchiidError(
                    f"{p}: directory{where} holds no image files "
                    f"({', '.join(sorted(IMAGE_SUFFIXES))}){hint}"
                )
            out.extend(InputItem(f, _key(f, p)) for f in found)
        elif not os.path.lexists(p) and _MAGIC & set(str(name)):
            out.extend(_expand_glob(str(name), excluded, skip))
        else:
            out.append(InputItem(p, p.stem))
    for list_file in lists:
        out.extend(read_list_file(Path(list_file)))
    return out


def file_identity(path: str | os.PathLike) -> str:
    """A file's path with symbolic links resolved, normalised and in the platform's case rule.

    Two names of one file (through a link, with ``..``, with either separator on Windows) give
    the same string: what ``skip`` of :func:`list_inputs` holds and compares.
    """
    return os.path.normcase(os.path.realpath(path))


def _identity(entry: os.DirEntry, real_folder: str) -> str:
    """:func:`file_identity` of a folder's entry, given the folder's own."""
    if entry.is_symlink():
        return file_identity(entry.path)
    return os.path.normcase(os.path.join(real_folder, entry.name))


def walks_into(inputs: Sequence[Path | str], folder: Path) -> bool:
    """Whether :func:`list_inputs` walks ``folder`` or a folder inside it for these inputs.

    That is: a folder named is ``folder`` or lies inside it, or a glob's fixed part does. (A
    walk from above leaves ``folder`` out when it is given as ``exclude``.)
    """
    target = os.path.realpath(folder)
    for name in inputs:
        p = Path(name)
        if p.is_dir():
            walked = p
        elif not os.path.lexists(p) and _MAGIC & set(str(name)):
            walked = _glob_root(str(name))
        else:
            continue
        real = os.path.realpath(walked)
        if real == target or real.startswith(target.rstrip(os.sep) + os.sep):
            return True
    return False


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def unique_keys(items: Sequence[InputItem]) -> list[InputItem]:
    """The items without repeats of the same file; raises if two would write the same outputs.

    Keys are compared without regard to case (:meth:`str.casefold`): ``IMG_0001.jpg`` and
    ``img_0001.png`` would write the same files on a case-insensitive disk (macOS, Windows, many
    network shares).

    Raises:
        TorchiidError: two different files have the same output key, or keys that differ only
            in case.
    """
    seen: set[str] = set()
    keys: dict[str, tuple[str, Path]] = {}
    unique = []
    for item in items:
        name = os.path.abspath(item.path)
        if name in seen:
            continue
        seen.add(name)
        folded = item.key.casefold()
        if folded in keys:
            other_key, other = keys[folded]
            if _same_file(other, item.path):  # one file named in two cases (macOS, Windows)
                continue
            case = "" if other_key == item.key else " (names that differ only in case)"
            raise TorchiidError(
                f"two inputs would write the same outputs{case}: {other} "
                f"and {item.path}; rename one or run them separately"
            )
        keys[folded] = (item.key, item.path)
        unique.append(item)
    return unique


def collect_inputs(inputs: Sequence[Path], *, recursive: bool = False) -> list[Path]:
    """Expand directories (and globs) into their image files (sorted); keep files as given.

    Args:
        inputs: Files, directories and glob patterns. A directory contributes its files whose
            suffix, in lower case, is one of :data:`IMAGE_SUFFIXES` (with ``recursive``, those
            of its subfolders too).
        recursive: descend into subfolders.

    Returns:
        The image paths, in the order given, each directory's files sorted.

    Raises:
        TorchiidError: A directory holds no image file, or a glob matches none.
    """
    return [item.path for item in list_inputs(inputs, recursive=recursive)]
