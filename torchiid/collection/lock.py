"""One run at a time per output folder: the lock file ``OUT/.torchiid.lock``.

A run takes an exclusive ``flock`` on the file for as long as it writes into the folder, and
removes the file when it ends. The kernel releases the lock when the process dies, however it
dies, so a file left by a killed run never blocks the next one. On NFS, Linux maps ``flock``
onto NFS byte-range locks, so runs on different machines exclude each other too. Where the file
system has no locks at all, the file is created exclusively instead and holds ``host`` and
``pid``; a file left by a dead process of the same host is taken over.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import time
from pathlib import Path

from torchiid.core.exceptions import TorchiidError
from torchiid.io.output_set import make_folders, remove_empty_folders

__all__ = ["LOCK_NAME", "FolderBusyError", "OutputLock"]

LOCK_NAME = ".torchiid.lock"


class FolderBusyError(TorchiidError):
    """Another run is writing into the output folder."""


def _holder(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def _busy(out: Path, holder: dict) -> FolderBusyError:
    who = ""
    if holder.get("pid"):
        who = f" (pid {holder['pid']} on {holder.get('host', '?')}, since {holder.get('since')})"
    return FolderBusyError(
        f"{out}: another torchiid run is writing into this folder{who}; wait for it to end "
        "or choose another output folder"
    )


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


class OutputLock:
    """The exclusive right to write into an output folder (see the module notes).

    Use as a context manager, or :meth:`acquire` and :meth:`release`. The folder (and missing
    parents) is created to hold the lock; :meth:`release` removes those it created again when
    they are empty.

    Args:
        out: the output folder.

    Raises:
        FolderBusyError: (from :meth:`acquire`) another run holds the lock.
        TorchiidError: the lock file cannot be created.
    """

    def __init__(self, out: str | os.PathLike) -> None:
        self.out = Path(out)
        self.path = self.out / LOCK_NAME
        self.existed = self.out.is_dir()
        self._fd: int | None = None
        self._exclusive = False
        self._created: list[Path] = []

    def __enter__(self) -> OutputLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> None:
        """Take the lock, or raise :class:`FolderBusyError`."""
        self._created = make_folders(self.out)
        try:
            self._acquire()
        except BaseException:
            self._remove_created()
            raise

    def _acquire(self) -> None:
        import fcntl

        for _ in range(20):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as exc:
                raise TorchiidError(
                    f"{self.path}: cannot create the lock file ({exc.strerror or exc})"
                ) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise _busy(self.out, _holder(self.path)) from None
            except OSError as exc:
                os.close(fd)
                if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                    self._acquire_exclusive()
                    return
                raise
            try:  # the holder before us may have removed the file: lock the one in place
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            self._fd = fd
            self._write_holder(fd)
            return
        raise TorchiidError(f"{self.path}: cannot take the lock (the file keeps changing)")

    def _write_holder(self, fd: int) -> None:
        text = json.dumps(
            {
                "host": socket.gethostname(),
                "pid": os.getpid(),
                "since": time.strftime("%Y-%m-%d %H:%M:%S"),
            }
        )
        os.ftruncate(fd, 0)
        os.pwrite(fd, text.encode(), 0)

    def _acquire_exclusive(self) -> None:
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                holder = _holder(self.path)
                pid = holder.get("pid")
                stale = (
                    isinstance(pid, int)
                    and pid > 0
                    and holder.get("host") == socket.gethostname()
                    and not _alive(pid)
                )
                if not stale:
                    raise _busy(self.out, holder) from None
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.path)
                continue
            self._fd, self._exclusive = fd, True
            self._write_holder(fd)
            return
        raise _busy(self.out, _holder(self.path))

    def release(self) -> None:
        """Give the lock up and remove the lock file (and empty folders the lock created)."""
        if self._fd is None:
            return
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)  # while still holding the lock
        os.close(self._fd)
        self._fd = None
        self._remove_created()

    def _remove_created(self) -> None:
        remove_empty_folders(self._created)
        self._created = []

    @property
    def held(self) -> bool:
        """This object holds the lock."""
        return self._fd is not None
