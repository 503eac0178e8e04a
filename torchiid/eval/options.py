"""The options of an evaluation run (:class:`EvalOptions`), checked when they are made."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from torchiid.core.exceptions import ParameterError
from torchiid.eval.methods import check_method
from torchiid.params import Parameters

__all__ = ["EvalOptions"]


@dataclass(frozen=True)
class EvalOptions:
    """How an evaluation run goes: the method, where it writes, which images, resuming.

    Construction checks the values; :class:`~torchiid.eval.runner.EvalRunner` checks what
    needs the file system (the folders) and resolves the device.

    Attributes:
        method: one of :data:`~torchiid.eval.methods.METHODS`; ignored when ``results_dir``
            is given.
        params: parameters of ``semantic`` (default: the ``default`` preset).
        output: output folder (default:
            :func:`~torchiid.eval.outputs.default_output_dir`, in the working directory).
        results_dir: score the layers in this folder (read with
            :func:`~torchiid.eval.results.load_layer`) instead of running ``method``; the
            run's method is then ``"results"``.
        device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda"`` or a
            :class:`torch.device`.
        batch_size: images of equal size decomposed together.
        limit: evaluate only the first ``limit`` images of the set.
        ids: ids to evaluate (a sequence or an id-list file), see
            :func:`~torchiid.eval.datasets.open_dataset`.
        input: MIT input image, ``"diffuse"`` or ``"original"``.
        delta: WHDR equality margin (``iiw``).
        resume: skip the ids already in ``results.csv``; if ``False``, an existing
            ``results.csv`` is an error.
        overwrite: discard existing results in the output folder and start over.
        progress: show a progress bar on stderr.
        on_failure: called with ``(id, exception)`` when an image fails (default: a
            warning on the ``torchiid.eval.runner`` logger).

    Raises:
        ParameterError: unknown method, ``batch_size < 1``, ``limit < 1``, or ``delta``
            negative or NaN.
    """

    method: str = "semantic"
    params: Parameters | None = None
    output: str | Path | None = None
    results_dir: str | Path | None = None
    device: str | torch.device = "auto"
    batch_size: int = 1
    limit: int | None = None
    ids: Sequence[str] | str | Path | None = None
    input: str = "diffuse"
    delta: float = 0.10
    resume: bool = True
    overwrite: bool = False
    progress: bool = False
    on_failure: Callable[[str, Exception], None] | None = None

    def __post_init__(self) -> None:
        check_method(self.method)
        check_ranges(self.batch_size, self.limit, self.delta)


def check_ranges(batch_size: int, limit: int | None, delta: float, *, flags: bool = False) -> None:
    """Raise :class:`ParameterError` for ``batch_size < 1``, ``limit < 1`` or a bad ``delta``.

    ``flags``: name the values as the command line does (``--batch-size``), not as fields.
    """

    def name(field: str) -> str:
        return f"--{field.replace('_', '-')}" if flags else field

    if batch_size < 1:
        raise ParameterError(f"{name('batch_size')} must be >= 1, got {batch_size}")
    if limit is not None and limit < 1:
        raise ParameterError(f"{name('limit')} must be >= 1, got {limit}")
    if not delta >= 0:
        raise ParameterError(f"{name('delta')} must be >= 0, got {delta}")


#: the names of the options
OPTION_NAMES = frozenset(f.name for f in dataclasses.fields(EvalOptions))
