"""What a collection's runner, its workers and its manifest pass around: jobs and results.

Plain data with no heavy imports, so that planning a run (reading the manifest, deciding
what to skip) loads no model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from torchiid.io.inputs import KeyParts

__all__ = ["ImageJob", "ImageResult", "InterruptedAfterCommit"]


@dataclass(frozen=True)
class ImageJob(KeyParts):
    """One image to process: where it is, where its outputs go, which attempt this is.

    Its output key's :attr:`stem` (the prefix of its file names) and :attr:`folder` (the
    output subfolder, ``""`` for the output folder itself) are properties.
    """

    index: int
    path: str
    key: str
    mask: str | None = None
    attempt: int = 1


@dataclass
class ImageResult:
    """What became of one image (one line of the manifest, see :mod:`.manifest`)."""

    index: int
    key: str
    path: str
    status: str  # "done" or "failed"
    message: str | None = None
    files: list[str] = field(default_factory=list)
    seconds: float = 0.0
    sha256: str | None = None
    size: int | None = None
    mtime_ns: int | None = None
    mask_sha256: str | None = None
    attempts: int = 1
    worker: str = ""
    recovered: bool = False
    note: str | None = None  # shown unless -q
    detail: str | None = None  # shown with -v
    failure: str | None = None  # "input", "output", "error" or "worker" (see process_image)

    @property
    def retryable(self) -> bool:
        """A failure that is not the input's nor the output folder's (Dask retries it)."""
        return self.failure == "error"

    @property
    def ok(self) -> bool:
        """The image's files are complete."""
        return self.status == "done"


class InterruptedAfterCommit(KeyboardInterrupt):  # noqa: N818 - it is an interrupt
    """An interrupt that arrived while the image's files were put in place: they are complete.

    Attributes:
        result: the image's (done) result, to be recorded before the run stops.
    """

    def __init__(self, result: ImageResult) -> None:
        super().__init__("interrupted after the files were put in place")
        self.result = result
