"""Collections: many photos, resumable, on many processes or a Dask cluster.

:func:`run_collection` decomposes a list of inputs (:func:`torchiid.io.inputs.list_inputs`)
into an output folder with a manifest (:mod:`.manifest`) that makes reruns skip what is done,
in this process, in ``workers`` processes (:mod:`.pool`) or on a Dask cluster
(:mod:`.dask_runner`); :func:`process_image` is what each of them does for one image.
The names below load on first use (:mod:`torchiid._lazy`): a rerun that finds every input
done plans from the manifest without loading torch or the model.
"""

from typing import TYPE_CHECKING

from torchiid._lazy import lazy_names

if TYPE_CHECKING:  # what static tools see; at run time: __getattr__
    from torchiid.collection.image_files import output_names
    from torchiid.collection.job import error_message, process_image
    from torchiid.collection.lock import FolderBusyError, OutputLock
    from torchiid.collection.manifest import MANIFEST_NAME, Manifest, ManifestWriter, Plan, plan
    from torchiid.collection.records import ImageJob, ImageResult, InterruptedAfterCommit
    from torchiid.collection.runner import (
        Progress,
        Reporter,
        RunInterrupted,
        RunSummary,
        run_collection,
    )
    from torchiid.collection.settings import RETINEX_DEFAULTS, RunSettings, file_sha256, params_hash
    from torchiid.collection.worker import SetupError, worker_state

__all__ = [
    "MANIFEST_NAME",
    "RETINEX_DEFAULTS",
    "FolderBusyError",
    "ImageJob",
    "ImageResult",
    "InterruptedAfterCommit",
    "Manifest",
    "ManifestWriter",
    "OutputLock",
    "Plan",
    "Progress",
    "Reporter",
    "RunInterrupted",
    "RunSettings",
    "RunSummary",
    "SetupError",
    "error_message",
    "file_sha256",
    "output_names",
    "params_hash",
    "plan",
    "process_image",
    "run_collection",
    "worker_state",
]

_SOURCES = {
    "output_names": "torchiid.collection.image_files",
    **dict.fromkeys(["error_message", "process_image"], "torchiid.collection.job"),
    **dict.fromkeys(
        ["ImageJob", "ImageResult", "InterruptedAfterCommit"], "torchiid.collection.records"
    ),
    **dict.fromkeys(["FolderBusyError", "OutputLock"], "torchiid.collection.lock"),
    **dict.fromkeys(
        ["MANIFEST_NAME", "Manifest", "ManifestWriter", "Plan", "plan"],
        "torchiid.collection.manifest",
    ),
    **dict.fromkeys(
        ["Progress", "Reporter", "RunInterrupted", "RunSummary", "run_collection"],
        "torchiid.collection.runner",
    ),
    **dict.fromkeys(
        ["RETINEX_DEFAULTS", "RunSettings", "file_sha256", "params_hash"],
        "torchiid.collection.settings",
    ),
    **dict.fromkeys(["SetupError", "worker_state"], "torchiid.collection.worker"),
}
__getattr__, __dir__ = lazy_names(__name__, _SOURCES, globals())
