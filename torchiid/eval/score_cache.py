"""Scores kept on disk between runs of the cross-validation tools, one JSON line per result."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["JsonlCache"]


class JsonlCache:
    """Scores kept on disk as JSON lines, one record per key, appended as they are computed.

    A key is the SHA-256 of the canonical JSON of whatever identifies a result (full
    parameters, sample, input file, code version): :meth:`key`. Lines that do not parse (a run
    killed mid-write) are skipped. ``folder=None`` keeps the records in memory only.
    """

    def __init__(self, folder: str | os.PathLike | None, name: str = "scores.jsonl") -> None:
        self.path = None if folder is None else Path(folder) / name
        self.records: dict[str, dict[str, Any]] = {}
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.is_file():
                for line in self.path.read_text(encoding="utf-8").splitlines():
                    try:
                        rec = json.loads(line)
                    except ValueError:
                        continue
                    if isinstance(rec, dict) and isinstance(rec.get("key"), str):
                        self.records[rec["key"]] = rec

    @staticmethod
    def key(**parts: Any) -> str:
        """SHA-256 hex digest of the parts' canonical JSON (sorted keys)."""
        text = json.dumps(parts, sort_keys=True, separators=(",", ":"), default=str)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    def get(self, key: str) -> dict[str, Any] | None:
        """The record stored under ``key``, or ``None``."""
        return self.records.get(key)

    def put(self, key: str, record: Mapping[str, Any]) -> None:
        """Store ``record`` under ``key`` (appended to the file at once)."""
        rec = {**record, "key": key}
        self.records[key] = rec
        if self.path is not None:
            with self.path.open("a", encoding="utf-8") as f:
                f.write(json.dumps(rec, sort_keys=True) + "\n")

    def __len__(self) -> int:
        return len(self.records)
