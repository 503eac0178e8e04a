"""The run manifest ``OUT/manifest.jsonl``: what became of every image, and what to skip.

One JSON object per line, appended and flushed (``fsync``) as each image ends; the last line
of a key is the one that counts. Fields:

==============  ===========================================================================
``key``         the output key (files ``OUT/<key>-*``)
``input``       absolute path of the input file
``sha256``      SHA-256 of the input file (``null`` if it could not be read)
``size``        its size in bytes, and ``mtime_ns`` its modification time (ns), at hashing
``mask``        absolute path of the image's own mask file (list files), or ``null``;
                ``mask_sha256`` its SHA-256
``params``      the parameters hash (:func:`~torchiid.collection.settings.params_hash`)
``status``      ``"done"`` or ``"failed"``
``message``     the one-line error of a failed image (``null`` when done)
``failure``     what failed: ``"input"`` (the file cannot be used), ``"output"`` (an output
                exists or cannot be written), ``"error"`` (unexpected, or more memory needed
                than was available: ``MemoryLimitError``) or ``"worker"`` (the worker
                process died on it every time); ``null`` when done
``files``       the output files, relative to ``OUT`` (``[]`` when failed)
``seconds``     time spent on the image
``attempts``    1, or more when a worker died while processing it and it was tried again
``worker``      ``host:pid`` of the process that processed it
``time``        when it ended (UTC, ISO 8601); ``torchiid_version`` the version of
                torchiid that wrote the line
==============  ===========================================================================

**Skipping on a rerun** (:func:`plan`): an input is skipped when its key's last record has the
same parameters hash, the same input SHA-256 (and mask SHA-256), and is ``done`` with every
listed file still present — or ``failed`` as a bad input (``"input"``), unless
``retry_failed``. Every other failure is tried again: ``"output"`` depends on the folder and on
``--overwrite``, ``"error"`` and ``"worker"`` on the process, the machine, the model, not on
the input. The input's SHA-256 is not recomputed when its path, size and modification time
(ns) are those recorded (the rule of make and rsync: a file rewritten with the same size within
the same nanosecond timestamp would be missed; ``redo`` recomputes everything); otherwise the
file is hashed again, so a touched but unchanged file is still skipped, and a refreshed record
(the new path, size and time; :attr:`Plan.refreshed`) is appended so that the next rerun need
not hash it again. The manifest is read once (one pass over its lines, a torn last line of a
killed run ignored; the next writer starts on a new line), each output folder is listed once,
and each input is ``stat``-ed once: a rerun over 10,000 done images takes seconds.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from torchiid._version import __version__
from torchiid.collection.records import ImageJob, ImageResult
from torchiid.collection.settings import file_sha256
from torchiid.io.inputs import InputItem

__all__ = [
    "MANIFEST_NAME",
    "Manifest",
    "ManifestWriter",
    "Plan",
    "plan",
    "read_records",
    "record_of",
]

log = logging.getLogger("torchiid")

MANIFEST_NAME = "manifest.jsonl"


def record_of(result: ImageResult, params: str, mask: str | None = None) -> dict:
    """The manifest line (as a dict) of one image's result."""
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    return {
        "key": result.key,
        "input": os.path.abspath(result.path),
        "sha256": result.sha256,
        "size": result.size,
        "mtime_ns": result.mtime_ns,
        "mask": os.path.abspath(mask) if mask else None,
        "mask_sha256": result.mask_sha256,
        "params": params,
        "status": result.status,
        "message": result.message,
        "failure": result.failure,
        "files": list(result.files),
        "seconds": round(result.seconds, 3),
        "attempts": result.attempts,
        "worker": result.worker,
        "time": now.replace("+00:00", "Z"),
        "torchiid_version": __version__,
    }


class Manifest:
    """The last record of every key in a manifest file (read once, in one pass).

    Args:
        path: the ``manifest.jsonl`` file; a missing file is an empty manifest.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.records: dict[str, dict] = {}
        self.bad_lines = 0
        self._written: set[str] = set()  # every "done" record's files, not the last ones only
        try:
            f = open(self.path, encoding="utf-8", errors="replace")
        except FileNotFoundError:
            return
        with f:
            for line in f:
                try:
                    record = json.loads(line)
                    self.records[record["key"]] = record
                except (ValueError, KeyError, TypeError):
                    self.bad_lines += 1  # a torn line of a killed run, or not ours
                    continue
                files = record.get("files")
                if record.get("status") == "done" and isinstance(files, list):
                    self._written.update(f for f in files if isinstance(f, str))
        if self.bad_lines:
            log.info("%s: %d unreadable line(s) ignored", self.path, self.bad_lines)

    def __len__(self) -> int:
        return len(self.records)

    def get(self, key: str) -> dict | None:
        """The last record of ``key``, or ``None``."""
        return self.records.get(key)

    def written_files(self, out: str | os.PathLike) -> set[str]:
        """The files that any ``done`` record says were written into ``out``.

        As :func:`torchiid.io.inputs.file_identity` names them. The outputs of the images
        done, by this run's parameters or earlier ones: a folder that is both an input and the
        output folder (``torchiid decompose photos -o photos``) would otherwise give them as
        new inputs on the next run (:func:`torchiid.io.inputs.list_inputs`, ``skip``).
        """
        from torchiid.io.inputs import file_identity

        base = os.path.realpath(out)
        return {file_identity(os.path.join(base, name)) for name in self._written}


class ManifestWriter:
    """Appends records to the manifest, one flushed and synced line per image.

    Args:
        path: the manifest file.
        eager: open it with the first record. Otherwise (a run that creates the output
            folder) records wait in memory until the first ``done`` one, so that a run in
            which every input fails leaves no manifest, like no output folder.
    """

    def __init__(self, path: str | os.PathLike, *, eager: bool = True) -> None:
        self.path = Path(path)
        self.eager = eager
        self.pending: list[dict] = []
        self.written = 0
        self._f = None

    def append(self, record: dict) -> None:
        """Write one record (or keep it, see ``eager``)."""
        self.pending.append(record)
        if self._f is None and not (self.eager or record["status"] == "done"):
            return
        text = ""
        if self._f is None:
            if _torn(self.path):  # a killed writer's last line: ours starts on a new one
                text = "\n"
            self._f = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - kept open
        text += "".join(json.dumps(r, allow_nan=False) + "\n" for r in self.pending)
        self._f.write(text)
        self._f.flush()
        os.fsync(self._f.fileno())
        self.written += len(self.pending)
        self.pending = []

    def close(self) -> None:
        """Close the file (records still waiting are dropped: nothing was done)."""
        if self._f is not None:
            self._f.close()
            self._f = None


def _torn(path: Path) -> bool:
    """The file exists, is not empty and does not end with a newline."""
    try:
        with open(path, "rb") as f:
            if f.seek(0, os.SEEK_END) == 0:
                return False
            f.seek(-1, os.SEEK_END)
            return f.read(1) != b"\n"
    except OSError:
        return False


class _Listing:
    """The names in each folder, listed once."""

    def __init__(self) -> None:
        self.names: dict[str, set[str]] = {}

    def exists(self, path: str) -> bool:
        folder, _, name = path.rpartition("/")
        names = self.names.get(folder)
        if names is None:
            try:
                names = set(os.listdir(folder or "."))
            except OSError:
                names = set()
            self.names[folder] = names
        return name in names


@dataclass
class Plan:
    """What a run does with each input (see :func:`plan`).

    Attributes:
        todo: the jobs to run, in input order.
        done_before: inputs skipped because they are done.
        failed_before: ``(input, record)`` of inputs skipped because they failed before.
        hashed: inputs whose SHA-256 was computed to decide (size or time changed).
        refreshed: records of skipped inputs that were hashed again and found unchanged, with
            their new path, size and time: appending them spares the next rerun the hashing.
    """

    todo: list[ImageJob] = field(default_factory=list)
    done_before: list[InputItem] = field(default_factory=list)
    failed_before: list[tuple[InputItem, dict]] = field(default_factory=list)
    hashed: int = 0
    refreshed: list[dict] = field(default_factory=list)


def _sha_of(path: Path, record: dict, plan_: Plan) -> tuple[str | None, dict | None]:
    """The file's SHA-256: the recorded one when path, size and time match, else hashed.

    ``None`` when the file cannot be read (as recorded for an input that could not be read).
    Second: when the file was hashed and is unchanged, its record with the new path, size and
    time (to append if the input is skipped), else ``None``.
    """
    try:
        st = os.stat(path)
    except OSError:
        return None, None
    name = os.path.abspath(path)
    same = (
        record.get("input") == name
        and record.get("size") == st.st_size
        and record.get("mtime_ns") == st.st_mtime_ns
    )
    if same:
        return record.get("sha256"), None
    try:
        plan_.hashed += 1
        sha = file_sha256(path)
    except OSError:
        return None, None
    if sha is None or sha != record.get("sha256"):
        return sha, None
    return sha, {**record, "input": name, "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def plan(
    items: Sequence[InputItem],
    manifest: Manifest,
    params: str,
    *,
    out: str | os.PathLike,
    retry_failed: bool = False,
    redo: bool = False,
) -> Plan:
    """Decide for each input: run it, or skip it as done or as failed before.

    Args:
        items: the inputs (unique keys).
        manifest: the output folder's manifest.
        params: the run's parameters hash.
        out: the output folder (to check that a done image's files are still there).
        retry_failed: run inputs whose last record is an ``"input"`` failure (else they are
            skipped; every other failure runs again anyway).
        redo: ignore the manifest: run every input.
    """
    result = Plan()
    listing = _Listing()
    out_prefix = os.fspath(out)
    mask_hashes: dict[str, str | None] = {}
    for index, item in enumerate(items):
        job = ImageJob(index, os.fspath(item.path), item.key, _str(item.mask))
        record = None if redo else manifest.get(item.key)
        if record is None or record.get("params") != params:
            result.todo.append(job)
            continue
        sha, refreshed = _sha_of(item.path, record, result)
        if sha != record.get("sha256"):  # None == None: still missing or unreadable
            result.todo.append(job)
            continue
        if item.mask is not None or record.get("mask_sha256") is not None:
            if item.mask is None:
                result.todo.append(job)
                continue
            name = os.path.abspath(item.mask)
            if name not in mask_hashes:
                try:
                    mask_hashes[name] = file_sha256(item.mask)
                except OSError:
                    mask_hashes[name] = None
            if mask_hashes[name] != record.get("mask_sha256"):
                result.todo.append(job)
                continue
        if record.get("status") == "done":
            files = record.get("files") or []
            if files and all(listing.exists(f"{out_prefix}/{f}") for f in files):
                result.done_before.append(item)
            else:
                result.todo.append(job)
                continue
        elif retry_failed or record.get("failure") != "input":
            result.todo.append(job)
            continue
        else:
            result.failed_before.append((item, record))
        if refreshed is not None:
            result.refreshed.append(refreshed)
    return result


def _str(path: Path | None) -> str | None:
    return None if path is None else os.fspath(path)


def read_records(path: str | os.PathLike) -> Iterable[dict]:
    """Every record of a manifest file, in order (for tools and tests)."""
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.strip():
                yield json.loads(line)
