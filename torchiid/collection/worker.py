"""What a process keeps between the images of a run, built once: :func:`worker_state`.

The torch threads, the device, the shared ``--mask`` and the feature extractor's session are
the same for every image of a run, so each process (the ``decompose`` process, a ``--workers``
process, a Dask worker) sets them up on its first image. A process that cannot be set up
raises :class:`SetupError`: not a fault of any image. The ``decompose`` process gives the
session back once its last image's features are computed (``release_models`` of
:func:`~.runner.run_collection`); a later run in that process loads it again.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

from torchiid.collection.settings import RunSettings
from torchiid.core.exceptions import TorchiidError, describe_error

__all__ = ["SetupError", "WorkerState", "worker_state"]


class SetupError(TorchiidError):
    """A process cannot be set up for the run: the model, the device or the ``--mask`` file.

    Not a fault of any image: the run stops (``decompose``, ``--workers``), or the image is
    recorded as an ``"error"`` failure that a rerun tries again (Dask).
    """


@dataclass
class WorkerState:
    """What a process keeps between the images of a run (see :func:`worker_state`)."""

    device: Any
    shared_mask: Any
    threads: int


_STATES: dict[tuple, WorkerState] = {}
_STATES_LOCK = threading.Lock()


def worker_state(settings: RunSettings) -> WorkerState:
    """This process's state for ``settings``, built on its first image and kept.

    Sets the torch threads (``settings.threads``), resolves the device, loads the ``--mask``
    file and, for the semantic method, loads the feature extractor (the ONNX session) once.

    Raises:
        SetupError: any of these failed (one line; the cause chained).
    """
    key = (
        settings.method,
        settings.device,
        str(settings.mask),
        settings.mask_sha256,
        settings.threads,
    )
    with _STATES_LOCK:  # a Dask worker may run several tasks at once
        state = _STATES.get(key)
        if state is None:
            try:
                state = _new_state(settings)
            except Exception as exc:  # noqa: BLE001 - whatever it is, no image can run
                raise SetupError(f"cannot set up the run: {describe_error(exc)}") from exc
            _STATES[key] = state
    return state


def _new_state(settings: RunSettings) -> WorkerState:
    import torch

    from torchiid.core.device import resolve_device
    from torchiid.core.memory import undo_malloc_trim_threshold
    from torchiid.io import load_mask

    undo_malloc_trim_threshold()  # Dask's nanny sets MALLOC_TRIM_THRESHOLD_: every tensor mmapped
    if settings.threads:
        torch.set_num_threads(settings.threads)
    device = resolve_device(settings.device)
    shared = load_mask(settings.mask) if settings.mask is not None else None
    if settings.method == "semantic":
        from torchiid.features.onnx_backend import OnnxFeatureExtractor

        OnnxFeatureExtractor(device=device.type)  # the session is cached for the process
    return WorkerState(device, shared, torch.get_num_threads())
