"""Output sets: the files of one image, put in place together or not at all.

One image's files are one **output set** (:class:`OutputSet`): they are written under their own
names into a hidden temporary folder ``.torchiid-<stem>-<random>`` inside the output folder and
renamed into place together only when every one of them is complete. An error, a
``KeyboardInterrupt`` (Ctrl-C) or SIGTERM before that removes the temporary folder, so the
output folder holds either nothing new or the complete set; SIGINT and SIGTERM arriving during
the renames are held until the set is in place. With ``overwrite`` the files of an old set are
replaced only then, and put back if a rename fails. The output folder (and missing parents) is
created when the first file of a set is written, and removed again when that set is discarded
and the folder is still empty. Only SIGKILL or a power loss can leave the hidden folder behind
(and, during the renames, a mix of old and new files, the old ones in that folder).

``TORCHIID_TEST_INTERRUPT`` (tests only) raises SIGINT in the process at a fixed point:
``write:N`` when the set's ``N + 1``-th file is about to be written, ``commit:N`` after the
``N``-th rename into place.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from torchiid.core.exceptions import TorchiidError

__all__ = [
    "OutputError",
    "OutputSet",
    "check_output_folder",
    "check_target",
    "make_folders",
    "missing_folders",
    "remove_empty_folders",
]


class OutputError(TorchiidError):
    """An output file or folder cannot be written (the message names it and says why)."""


def _why(exc: OSError) -> str:
    return exc.strerror or " ".join(str(exc).split()) or type(exc).__name__


def missing_folders(folder: Path) -> list[Path]:
    """``folder`` and those of its parents that do not exist, innermost first."""
    missing = []
    here = folder
    while not here.exists() and here != here.parent:
        missing.append(here)
        here = here.parent
    return missing


def make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; returns the folders it created, innermost first.

    Raises:
        OutputError: the folder cannot be created (the message names it and says why).
    """
    missing = missing_folders(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot create the output folder ({_why(exc)})") from None
    finally:
        created = [d for d in missing if d.is_dir()]
    return created


def remove_empty_folders(created: list[Path]) -> None:
    """Remove folders made by :func:`make_folders` (innermost first) while they are empty."""
    for folder in created:
        try:
            folder.rmdir()
        except OSError:
            break


def check_target(target: Path, overwrite: bool) -> None:
    """Raise :class:`OutputError` if ``target`` is a folder, or exists without ``overwrite``."""
    if target.is_dir() and not target.is_symlink():
        raise OutputError(f"{target}: is a folder; cannot replace it by an output")
    if not overwrite and os.path.lexists(target):
        raise OutputError(f"{target} exists; pass --overwrite to replace it")


_HELD = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM during the block and deliver them after it (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous: dict[int, Any] = {}
    for sig in _HELD:
        handler = signal.getsignal(sig)
        if handler is None or handler is signal.SIG_IGN:
            continue  # installed outside Python, or ignored: leave it alone
        previous[sig] = signal.signal(sig, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if received:
            signal.raise_signal(received[0])


def _test_interrupt(stage: str, count: int) -> None:
    """The ``TORCHIID_TEST_INTERRUPT`` hook of the tests (see the module notes)."""
    want = os.environ.get("TORCHIID_TEST_INTERRUPT")
    if want and want == f"{stage}:{count}":
        signal.raise_signal(signal.SIGINT)


class OutputSet:
    """The files of one image, written under temporary names and put in place together.

    Write each file with :meth:`write`, then call :meth:`commit`; used as a context manager,
    the set is discarded (temporary files removed, nothing else touched) when the block ends
    with an exception, ``KeyboardInterrupt`` included, and is otherwise left to the caller to
    commit. See the module notes for the guarantees.

    Args:
        out_dir: the output folder; created, with missing parents, by the first :meth:`write`.
        overwrite: replace existing files of the same names at :meth:`commit` (else an existing
            file makes the commit fail and the old file stays as it was).
        label: part of the temporary folder's name (e.g. the image's stem).

    Raises:
        OutputError: (from :meth:`write` and :meth:`commit`) a file or folder cannot be
            written; the message names the output file, never a temporary name.
    """

    def __init__(
        self, out_dir: str | os.PathLike, *, overwrite: bool = True, label: str = "set"
    ) -> None:
        self.out = Path(out_dir)
        self.overwrite = overwrite
        self.label = label
        self.names: list[str] = []
        self.committed = False
        self._tmp: Path | None = None
        self._created: list[Path] = []
        self._pending: list[Future[None]] = []  # files being written in the background
        self._pool: ThreadPoolExecutor | None = None

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if kind is not None:
            self.discard()

    def _start(self) -> Path:
        self._created = make_folders(self.out)
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".torchiid-{self.label}-", dir=self.out))
            (self._tmp / "new").mkdir()
        except OSError as exc:
            self.discard()
            raise OutputError(
                f"{self.out}: cannot write into the output folder ({_why(exc)})"
            ) from None
        return self._tmp

    def write(self, name: str, write: Callable[[Path], Any], *, background: bool = False) -> Path:
        """Let ``write(path)`` write the file ``name`` of the set; returns its final path.

        ``background``: run ``write`` on the set's writer threads (as many as torch's threads)
        and return at once, so that several files are encoded at the same time (OpenCV and
        OpenEXR release the GIL). The file keeps its place in the set's order; :meth:`wait`
        and :meth:`commit` wait for it and raise its error, and :meth:`discard` lets it
        finish before removing anything. The writers take the files in the order given.
        """
        if "/" in name or os.sep in name or name in ("", ".", ".."):
            raise ValueError(f"an output file name must be a plain name, got {name!r}")
        if name in self.names:
            raise ValueError(f"{name} is already part of this output set")
        _test_interrupt("write", len(self.names))
        tmp = self._tmp if self._tmp is not None else self._start()
        self.names.append(name)
        if background:
            job = self._writers().submit(self._write, name, write, tmp / "new" / name)
            self._pending.append(job)
        else:
            self._write(name, write, tmp / "new" / name)
        return self.out / name

    def _writers(self) -> ThreadPoolExecutor:
        if self._pool is None:
            import torch  # here: the output folder checks run before torch is imported

            threads = max(1, torch.get_num_threads())
            self._pool = ThreadPoolExecutor(threads, thread_name_prefix="torchiid-write")
        return self._pool

    def _write(self, name: str, write: Callable[[Path], Any], path: Path) -> None:
        try:
            write(path)
        except OSError as exc:
            raise OutputError(f"{self.out / name}: cannot write ({_why(exc)})") from None

    def wait(self) -> None:
        """Wait for the files being written in the background; raise the first one's error.

        On an error (or an interrupt while waiting) the writes not yet started are cancelled
        and the running ones finish before it is raised.
        """
        pending, self._pending = self._pending, []
        try:
            for future in pending:
                future.result()
        except BaseException:
            _settle(pending)
            raise

    def commit(self) -> list[Path]:
        """Wait for the background writes, then rename every file of the set into place.

        Returns:
            The files' final paths, in the set's order.

        Raises:
            OutputError: a target is a folder, a target exists without ``overwrite``, or a
                rename failed; the old files are back in place and the new ones removed.
                A background write's error is raised before anything is renamed (the set
                is then discarded by its ``with`` block).
        """
        self.wait()
        self._stop_writers()
        if self._tmp is None:
            return []
        new, old = self._tmp / "new", self._tmp / "old"
        targets = [self.out / n for n in self.names]
        with _signals_held():
            try:
                for target in targets:
                    check_target(target, self.overwrite)
                moved: list[tuple[Path, Path]] = []
                placed: list[Path] = []
                try:
                    old.mkdir()
                    for name, target in zip(self.names, targets, strict=True):
                        if os.path.lexists(target):
                            os.replace(target, old / name)
                            moved.append((old / name, target))
                        os.replace(new / name, target)
                        placed.append(target)
                        _test_interrupt("commit", len(placed))
                except OSError as exc:
                    for path in reversed(placed):
                        with contextlib.suppress(OSError):
                            os.unlink(path)
                    for backup, target in reversed(moved):
                        with contextlib.suppress(OSError):
                            os.replace(backup, target)
                    where = targets[len(placed)] if len(placed) < len(targets) else self.out
                    raise OutputError(f"{where}: cannot write ({_why(exc)})") from None
                self.committed = True
            finally:
                self._remove_tmp()
            self._created = []  # they hold the set now
        return targets

    def discard(self) -> None:
        """Remove the temporary files, and the folders the set created if they are empty."""
        pending, self._pending = self._pending, []
        _settle(pending)  # no write may still be running in the folder it removes
        self._stop_writers()
        with _signals_held():
            self._remove_tmp()
            remove_empty_folders(self._created)
            self._created = []

    def _stop_writers(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _remove_tmp(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None


def _settle(futures: list[Future[None]]) -> None:
    """Cancel the writes not yet started and wait for the running ones (errors ignored)."""
    for future in futures:
        future.cancel()
    concurrent.futures.wait(futures)


def check_output_folder(out_dir: str | os.PathLike) -> None:
    """Check, before any work, that output files can be written into ``out_dir``.

    An existing folder is probed by creating (and removing) a hidden file in it; a missing one
    is not created (:class:`OutputSet` creates it with the first file), but its nearest
    existing parent must be a folder in which a folder can be created (probed likewise).

    Raises:
        OutputError: ``out_dir`` or one of its parents is a file, or nothing can be created
            there; the message names the folder and the reason.
    """
    out = Path(out_dir)
    if out.exists():
        if not out.is_dir():
            raise OutputError(f"{out}: output exists and is not a directory")
        try:
            fd, probe = tempfile.mkstemp(prefix=".torchiid-probe-", dir=out)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise OutputError(f"{out}: cannot write into the output folder ({_why(exc)})") from None
        return
    parent = out
    while not parent.exists():
        if parent.is_symlink():
            raise OutputError(f"{out}: cannot create the output folder: {parent} is a broken link")
        if parent == parent.parent:
            break
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{out}: cannot create the output folder: {parent} is not a directory")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".torchiid-probe-", dir=parent))
    except OSError as exc:
        raise OutputError(
            f"{out}: cannot create the output folder in {parent} ({_why(exc)})"
        ) from None
