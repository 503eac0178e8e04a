"""The memory a decomposition takes, estimated before any work, and the check against it."""

from __future__ import annotations

import os

from torchiid.core.exceptions import MemoryLimitError
from torchiid.core.memory import MEMORY_LIMIT_VARIABLE, available_memory, memory_limit
from torchiid.params import Parameters
from torchiid.priors.reflectance_terms import REPLAY_STEPS
from torchiid.resample import working_size

__all__ = [
    "BYTES_PER_WORKING_PIXEL",
    "BYTES_PER_FULL_PIXEL",
    "MEMORY_OVERHEAD",
    "MEMORY_CHECK_VARIABLE",
    "memory_needed",
    "check_memory",
]

#: Peak memory the method takes per pixel of the working resolution, on the CPU: the growth
#: of a ``torchiid decompose --max-side 0`` process's peak RSS above its own footprint,
#: fitted on photos of 0.5 to 2 MP (``python tools/bench_memory.py``), with the ``default``
#: solvers (the Split-Bregman state replayed) and with the state stored between updates, as
#: in the ``converged`` preset (its 60-plane state per channel and the multigrid hierarchy).
#: Less the per-pixel cost of the full resolution below.
BYTES_PER_WORKING_PIXEL = {"replayed": 1240, "stored": 1990}
#: and per pixel of the input, beyond it: the photo, the layers and their bands
BYTES_PER_FULL_PIXEL = 50
#: and once per call: the features' and the solvers' own buffers
MEMORY_OVERHEAD = 150_000_000
#: the environment variable that switches the check off (``TORCHIID_MEMORY_CHECK=0``)
MEMORY_CHECK_VARIABLE = "TORCHIID_MEMORY_CHECK"


def memory_needed(
    height: int,
    width: int,
    params: Parameters | None = None,
    batch: int = 1,
    *,
    return_stage1: bool = False,
    return_iterations: bool = False,
) -> int:
    """Bytes a decomposition of ``batch`` images of ``height × width`` takes beyond what is loaded.

    An estimate of the peak growth on the CPU: :data:`BYTES_PER_WORKING_PIXEL` per pixel of
    the working resolution ``params.output.max_side``, :data:`BYTES_PER_FULL_PIXEL` per pixel
    of the input and :data:`MEMORY_OVERHEAD`, fitted on photos (how well it fits whole
    processes: the documentation's Benchmarks page, "Memory estimate"); with
    ``return_stage1`` (:func:`~torchiid.model.decompose`'s default) 16 bytes more per input
    pixel (``σ, ρ`` at full resolution), with ``return_iterations`` 32 bytes per working pixel
    and alternation (``σ, ρ, R, S``). The libraries and the feature extractor, loaded once per
    process (about 0.5 GB), are not in it.
    """
    params = params if params is not None else Parameters.preset("default")
    h, w = working_size(height, width, params.output.max_side)
    r = params.reflectance
    stored = r.bregman_warm_state or r.bregman_iter > REPLAY_STEPS + 1
    per_working = BYTES_PER_WORKING_PIXEL["stored" if stored else "replayed"]
    if return_iterations:
        per_working += 32 * params.iterations
    per_full = BYTES_PER_FULL_PIXEL + (16 if return_stage1 else 0)
    return MEMORY_OVERHEAD + batch * (per_working * h * w + per_full * height * width)


def _gb(n: float) -> str:
    """Bytes as GB: ``0.001 GB`` (below 0.01 GB), ``0.25 GB``, ``31.2 GB`` (from 10 GB).

    Small figures keep their first significant digits, so a small limit is not shown as 0.
    """
    if n < 0.01e9:
        return f"{n / 1e9:.2g} GB"
    return f"{n / 1e9:.2f} GB" if n < 10e9 else f"{n / 1e9:.1f} GB"


def check_memory(
    height: int,
    width: int,
    params: Parameters | None = None,
    batch: int = 1,
    *,
    limit: int | None = None,
    return_stage1: bool = False,
    return_iterations: bool = False,
) -> None:
    """Refuse, before any work, a CPU decomposition that cannot fit in the memory it may take.

    What it may take is what the machine has left (:func:`~torchiid.core.memory.available_memory`),
    or less: a cap the user set (``limit``, else ``TORCHIID_MEMORY_LIMIT`` in GB, see
    :func:`~torchiid.core.memory.memory_limit`). :func:`~torchiid.model.decompose` runs this
    check itself (without ``limit``); an application that holds a cap of its own calls it first
    with it. ``TORCHIID_MEMORY_CHECK=0`` switches off the comparison with what the machine has
    left; a cap the user set still holds.

    Args:
        height: the photo's height in pixels.
        width: its width.
        params: the parameters (their working resolution and solvers count).
        batch: images decomposed together.
        limit: a cap in bytes (``None``: ``TORCHIID_MEMORY_LIMIT``, if set).
        return_stage1: the decomposition is asked to keep the Stage 1 layers.
        return_iterations: and every alternation's layers.

    Raises:
        MemoryLimitError: the estimate (:func:`memory_needed`) is over the cap or what is
            left; the message gives both figures and what to change.
        ParameterError: ``TORCHIID_MEMORY_LIMIT`` is not a number of GB.
    """
    params = params if params is not None else Parameters()
    cap = memory_limit() if limit is None else limit
    flags = {"return_stage1": return_stage1, "return_iterations": return_iterations}
    need = memory_needed(height, width, params, batch, **flags)
    have = None
    switch = os.environ.get(MEMORY_CHECK_VARIABLE, "1").strip().lower()
    if switch not in ("0", "off", "false", "no"):
        try:
            have = available_memory()
        except Exception:  # noqa: BLE001 - the check must never be what breaks a decomposition
            have = None
    capped = cap is not None and (have is None or cap <= have)
    budget = cap if capped else have
    if budget is None or need <= budget:
        return
    h, w = working_size(height, width, params.output.max_side)
    where = "at full resolution" if (h, w) == (height, width) else f"at {w}x{h} px"
    many = f"{batch} images of " if batch > 1 else ""
    hint = ""
    default_side = Parameters().output.max_side
    if max(h, w) > default_side:
        at_default = params.replace(max_side=default_side)
        fit = memory_needed(height, width, at_default, batch, **flags)
        what = f"--max-side {default_side}, the default (max_side in Python)"
        if fit <= budget:
            hint = f"with {what}, it needs about {_gb(fit)}; "
        else:
            hint = f"even with {what}, it needs about {_gb(fit)}; "
    needs = f"decomposing {many}{width}x{height} px {where} needs about {_gb(need)} of memory"
    if capped:
        raise MemoryLimitError(
            f"{needs}, over the memory limit of {_gb(budget)}; {hint}raise the limit "
            f"(--memory-limit GB, or {MEMORY_LIMIT_VARIABLE}) to try it"
        )
    raise MemoryLimitError(
        f"{needs} and {_gb(have)} is available; {hint}set {MEMORY_CHECK_VARIABLE}=0 to try anyway"
    )
