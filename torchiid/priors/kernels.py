"""Compiled CPU kernels for the stencil products (numba), with the torch ops as the reference.

The solvers spend most of their time in weighted Laplacian products ``Mᵀ diag(w) M x`` over
both directions of every pair of a stencil: the shading PCG (a 5×5 stencil, 12 offsets) and
the Split-Bregman ``z`` step (an 11×11 stencil, 60 offsets, 3 channels). In torch each
direction of each offset is one strided ``addcmul`` over the whole image, ``2K`` passes over
memory per product. The kernel does one pass: every output row gathers its ``2K`` terms while
the rows it reads are in cache (``python tools/bench_kernels.py`` prints the comparison).

The kernel sums the pairs in difference form, ``Σ w (x_i − x_j)``, where the torch ops use
``deg ⊙ x − Σ w x_j``: the same operator, but it annihilates constants exactly and keeps its
round-off relative to the differences rather than to the values. That matters for the
``converged`` preset's float32 shading solves, which sit at the edge of what float32 resolves:
with the ``deg`` form in the kernel, chelsea's second shading solve broke down after 2
iterations (and was redone in float64, 1.2 s); with the difference form it converges in 14
float32 iterations, as with the torch ops.

The same one-pass kernels build the reflectance stage's 60-offset colour weights and the
matting Laplacian's stencil (once per alternation each).

Threads: as many as torch uses (``torch.get_num_threads()``). The stencil product runs on
numba's thread pool, one call at a time (numba's fallback threading layer aborts on
concurrent calls); the weight builders split the image's rows into bands and run them at
once on a small Python thread pool (the kernels release the GIL). Small calls and one-thread
processes run on the calling thread only. Each output element is computed by one thread in
a fixed order, so the result does not depend on the number of threads.

The kernels are used only where they apply (:func:`usable`): numba importable, CPU tensors of
float32 or float64, and no autograd graph to record (the differentiable losses keep the torch
ops). ``TORCHIID_KERNELS=torch`` in the environment turns them off, e.g. to compare the two
paths. The first use in a Python environment compiles them (about 5 s, once: numba caches
the machine code on disk for every later process).
"""

from __future__ import annotations

import logging
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from functools import cache

import torch

from torchiid.core.exceptions import ParameterError, ShapeError

__all__ = [
    "usable",
    "stencil_product",
    "stencil_degree",
    "stencil_affinity",
    "matting_window_terms",
    "bregman_replay",
    "bregman_update",
    "fixed_point_scales",
    "fixed_point_fits",
    "matting_weights",
]

logger = logging.getLogger(__name__)


@cache
def _numba():
    """The compiled kernel, or ``None`` without numba (or with ``TORCHIID_KERNELS=torch``)."""
    if os.environ.get("TORCHIID_KERNELS", "").lower() == "torch":
        return None
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; kept for slim installs
        return None
    try:
        from torchiid.priors import stencil_kernels
    except Exception as exc:  # pragma: no cover - e.g. no writable directory for numba's cache
        logger.warning("compiled kernels unavailable (%s); using the torch ops", exc)
        return None
    return numba, stencil_kernels


def usable(*tensors: torch.Tensor, offsets: list[tuple[int, int]] | None = None) -> bool:
    """Whether the compiled kernels apply to these tensors (see the module notes).

    With ``offsets``, also whether they are half offsets (``dy >= 0``), the only ones the
    kernels handle (:func:`~torchiid.priors.stencil.half_offsets` gives such).
    """
    if _numba() is None:
        return False
    if offsets is not None and any(dy < 0 for dy, _ in offsets):
        return False
    dtype = tensors[0].dtype
    if dtype not in (torch.float32, torch.float64):
        return False
    grad = torch.is_grad_enabled()
    return all(
        t.device.type == "cpu" and t.dtype == dtype and not (grad and t.requires_grad)
        for t in tensors
    )


@cache
def _offsets(offsets: tuple[tuple[int, int], ...]):
    import numpy as np

    arr = np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
    return np.ascontiguousarray(arr[:, 0]), np.ascontiguousarray(arr[:, 1])


def stencil_product(
    x: torch.Tensor,
    weights: torch.Tensor,
    offsets: list[tuple[int, int]],
    square: bool = False,
) -> torch.Tensor:
    """``Mᵀ diag(w) M x``: ``Σ_k w_k(i) (x_i − x_{i+o_k}) + Σ_k w_k(i − o_k) (x_i − x_{i−o_k})``.

    One pass, summed in the input's dtype in difference form (see the module notes); only
    the pairs inside the image are read. ``x`` and ``weights`` must have the same batch size.

    Args:
        x: ``(B, C, H, W)``.
        weights: ``(B, K, H, W)`` pair weights indexed by the first pixel (may be signed).
        offsets: the ``K`` half offsets ``(dy, dx)`` with ``dy >= 0``.
        square: use ``w_k²`` in place of ``w_k`` (squared on the fly; saves storing them).

    Returns:
        A new ``(B, C, H, W)`` tensor.
    """
    return _gather(x.contiguous(), weights, offsets, square, degree=False)


def stencil_degree(
    weights: torch.Tensor, offsets: list[tuple[int, int]], square: bool = False
) -> torch.Tensor:
    """Each pixel's summed pair weights ``Σ_k w_k(i) + Σ_k w_k(i − o_k)`` over the pairs inside.

    ``(B, K, H, W) -> (B, 1, H, W)``, summed in the weights' dtype.
    """
    b, _, h, w = weights.shape
    shape_only = torch.empty(b, 1, h, w, dtype=weights.dtype)
    return _gather(shape_only, weights, offsets, square, degree=True)


def _gather(x, weights, offsets, square: bool, degree: bool) -> torch.Tensor:
    numba, kernel = _numba()
    dys, dxs = _offsets(tuple(offsets))
    out = torch.empty_like(x)
    b, _, h, _ = x.shape
    args = (x.numpy(), weights.contiguous().numpy(), dys, dxs, out.numpy(), square, degree)
    n = min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
    if n <= 1:
        kernel.gather(*args, 0, b * h)
    else:  # numba's pool: a cheaper hand-off than bands for a sub-millisecond call
        # one caller at a time: numba's fallback threading layer (workqueue, where neither
        # OpenMP nor TBB is available) aborts the process on concurrent parallel calls
        with _parallel_lock:
            numba.set_num_threads(n if x.numel() * 2 * len(offsets) >= PARALLEL_WORK else 1)
            kernel.gather_parallel(*args)
    return out


#: below this many multiply-adds a call runs on the calling thread only: handing bands to
#: the pool costs more than it saves
PARALLEL_WORK = 1 << 21

_parallel_lock = threading.Lock()
_pool_lock = threading.Lock()
_pool: tuple[int, int, ThreadPoolExecutor] | None = None  # (pid, workers, pool)


def _executor(workers: int) -> ThreadPoolExecutor:
    """The process's band pool with at least ``workers`` threads (a new one after a fork)."""
    global _pool
    with _pool_lock:
        if _pool is None or _pool[0] != os.getpid() or _pool[1] < workers:
            if _pool is not None and _pool[0] == os.getpid():
                _pool[2].shutdown(wait=False)  # a smaller pool: let its threads end
            _pool = (os.getpid(), workers, ThreadPoolExecutor(workers, "torchiid-kernel"))
        return _pool[2]


def _run(kernel, args: tuple, rows: int, work: int) -> None:
    """``kernel(*args, r0, r1)`` over ``rows`` rows, in bands on torch's thread count."""
    n = min(torch.get_num_threads(), rows)
    if n <= 1 or work < PARALLEL_WORK:
        kernel(*args, 0, rows)
        return
    cuts = [rows * i // n for i in range(n + 1)]
    pool = _executor(n - 1)
    futures = [pool.submit(kernel, *args, cuts[i], cuts[i + 1]) for i in range(1, n)]
    kernel(*args, cuts[0], cuts[1])
    for f in futures:
        f.result()


def bregman_replay(
    history: list[torch.Tensor],
    z: torch.Tensor,
    weights: torch.Tensor,
    offsets: list[tuple[int, int]],
    lam: float,
) -> torch.Tensor:
    """The right-hand side of a ``StencilL1Term`` Bregman update, its state replayed.

    ``Σ_k (W M)ᵀ (d_k − b_k)`` at ``z`` for a solve that started from the zero state and made
    its earlier updates at the ``z`` in ``history`` (oldest first): each pair's Bregman
    variable is recomputed from them instead of read from a stored ``(B, C, K, H, W)``
    state (:func:`bregman_update` with a history and no state).

    Shape:
        history items and z ``(B, C, H, W)``, weights ``(B, K, H, W)`` -> ``(B, C, H, W)``.
    """
    return bregman_update(z, weights, offsets, lam, history=history)


def bregman_update(
    z: torch.Tensor,
    weights: torch.Tensor,
    offsets: list[tuple[int, int]],
    lam: float,
    *,
    state: torch.Tensor | None = None,
    read: bool = False,
    write: bool = False,
    history: list[torch.Tensor] | tuple[()] = (),
    state_step: float = 1.0,
    stats: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A ``StencilL1Term`` Bregman update at ``z``: its right-hand side, ``state`` updated.

    Every pair's Bregman variable starts from ``state`` (``read``) or from 0, is replayed
    through the updates at the ``z`` in ``history`` (oldest first), is updated at ``z`` and
    written back to ``state`` (``write``); returns ``Σ_k (W M)ᵀ (d_k − b_k)`` (see
    ``stencil_kernels._bregman_update``). One pass over the state where the torch path makes
    about ten per offset. The rows are cut into blocks of :data:`REPLAY_BLOCK_ROWS`, run in
    runs of whole blocks on torch's thread count; each block's contributions to the rows
    after it are added once all blocks are done, in block order, so the result does not
    depend on the number of threads.

    A ``torch.int16`` state holds the variable in 16-bit fixed point (see
    :func:`fixed_point_scales`): it is read as ``q · state_step`` and written with the step
    of ``lam``.

    ``stats=True`` also measures the update (the kernel's measured mode: the same state and
    right-hand side) and returns ``(rhs, adj, sums)``: ``adj = (W M)ᵀ b'`` ``(B, C, H, W)``
    and per image ``(B, 4)`` float64 sums of ``|W M z|``, ``(b' − b)²``, ``(W M z)²`` and
    ``d²``.

    Shape:
        z and history items ``(B, C, H, W)``, weights ``(B, K, H, W)``, state ``(B, C, K, H,
        W)`` contiguous (``z``'s dtype or ``torch.int16``) -> ``(B, C, H, W)``.
    """
    import numpy as np

    _, kernel = _numba()
    dys, dxs = _offsets(tuple(offsets))
    b, c, h, w = z.shape
    if (read or write) and (
        state is None or state.shape != (b, c, len(offsets), h, w) or not state.is_contiguous()
    ):
        raise ShapeError(
            f"state must be a contiguous {(b, c, len(offsets), h, w)} tensor to read or write"
        )
    if state is not None and state.dtype not in (z.dtype, torch.int16):
        raise ShapeError(f"state must be {z.dtype} or torch.int16, got {state.dtype}")
    zs = torch.stack([*history, z]).contiguous()
    rhs = torch.empty(b, c, h, w, dtype=z.dtype)
    st = state if state is not None else torch.empty(0, 0, 0, 0, 0, dtype=z.dtype)
    ftype = rhs.numpy().dtype.type
    fixed = st.dtype == torch.int16
    scale_in = ftype(state_step if fixed else 1.0)
    inv_out = ftype(fixed_point_scales(lam)[1] if fixed else 0.0)
    depth = max(1, int(dys.max()))
    rows = b * h
    block = REPLAY_BLOCK_ROWS
    blocks = -(-rows // block)
    n = min(torch.get_num_threads(), blocks)
    work = rows * w * len(offsets) * c * (4 + 3 * len(history))
    if n <= 1 or work < PARALLEL_WORK:
        n = 1
    cuts = [blocks * i // n for i in range(n + 1)]  # each thread: a run of whole blocks
    dtype = rhs.numpy().dtype
    halo = np.empty((blocks, depth, c, w), dtype=dtype)
    # the measured update's outputs, or empty arrays (the kernel leaves them alone)
    adj = torch.empty_like(rhs) if stats else torch.empty(0, 0, 0, 0, dtype=z.dtype)
    halo2 = np.empty_like(halo) if stats else np.empty((0, 0, 0, 0), dtype=dtype)
    sums = np.empty((blocks if stats else 0, b, 4), dtype=np.float64)
    args = (
        zs.numpy(),
        weights.contiguous().numpy(),
        dys,
        dxs,
        dtype.type(lam),
        st.numpy(),
        bool(read),
        bool(write),
        scale_in,
        inv_out,
        rhs.numpy(),
        halo,
        adj.numpy(),
        halo2,
        sums,
        block,
    )
    fn = kernel.bregman_update
    if n == 1:
        fn(*args, 0, blocks)
    else:
        pool = _executor(n - 1)
        futures = [pool.submit(fn, *args, cuts[i], cuts[i + 1]) for i in range(1, n)]
        fn(*args, cuts[0], cuts[1])
        for f in futures:
            f.result()
    kernel.add_halos(rhs.numpy(), halo, block)
    if not stats:
        return rhs
    kernel.add_halos(adj.numpy(), halo2, block)
    return rhs, adj, torch.from_numpy(sums.sum(axis=0))


#: the largest magnitude of a 16-bit fixed-point Bregman variable: ``λ`` is stored as this
STATE_LEVELS = 32767


def fixed_point_scales(lam: float) -> tuple[float, float]:
    """``(step, inverse)`` of a 16-bit fixed-point Bregman variable written at threshold ``λ``.

    The variable lies in ``[−λ, λ]`` (it is clamped there), so it is stored as ``q =
    rint(b · inverse)``, an integer in ``[−32767, 32767]``, and read back as ``q · step``: an
    absolute error of at most ``λ / 65534``. Both are float32 numbers, so that the torch ops
    and the compiled kernel compute the same values.
    """
    scales = _scales(lam)
    if scales is None:
        raise ParameterError(
            f"Split-Bregman threshold λ = γ / θ = {lam!r} cannot be kept in a 16-bit state "
            f"(its step λ / {STATE_LEVELS} is not a normal float32 number); keep such a "
            "state in float32 instead (the pipeline does so by itself)"
        )
    return scales


def fixed_point_fits(lam: float) -> bool:
    """Whether a Bregman variable of threshold ``λ`` can be kept in 16-bit fixed point."""
    return _scales(lam) is not None


def _scales(lam: float) -> tuple[float, float] | None:
    import numpy as np

    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        step = np.float32(lam / STATE_LEVELS) if lam > 0 else np.float32(0)
        inverse = np.float32(STATE_LEVELS / lam) if lam > 0 else np.float32(np.inf)
    tiny = np.finfo(np.float32).tiny
    if not (step >= tiny and np.isfinite(step) and np.isfinite(inverse)):
        return None
    return float(step), float(inverse)


#: rows per block of :func:`bregman_update` (fixed, so that the result does not depend on
#: the thread count)
REPLAY_BLOCK_ROWS = 32


def matting_window_terms(
    image: torch.Tensor, eps: float, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """The matting Laplacian's per-window summands in one pass, for :func:`matting_weights`.

    Args:
        image: ``(B, 3, H, W)`` float64 centred base image, ``H, W >= 3``.
        eps: Levin's regulariser.
        mask: optional ``(B, 1, H, W)`` bool; windows with a pixel outside it get 0.

    Returns:
        ``(B, 11, H + 2, W + 2)`` float64: window ``(wy, wx)`` at ``(wy + 2, wx + 2)``, 0
        around (the layout of ``MattingQuadratic.as_stencil``'s torch ops).
    """
    _, kernel = _numba()
    b, _, h, w = image.shape
    qp = torch.empty(b, 11, h + 2, w + 2, dtype=torch.float64)
    qp[:, :, :2].zero_()  # the kernel writes every other entry (the window rows' borders too)
    qp[:, :, h:].zero_()
    m = torch.empty(0, 0, 0, 0, dtype=torch.bool)
    if mask is not None:
        m = mask.to(torch.bool).contiguous()
    args = (image.contiguous().numpy(), m.numpy(), float(eps), qp.numpy())
    _run(kernel.matting_windows, args, b * (h - 2), b * h * w * 120)
    return qp


def matting_weights(
    window_terms: torch.Tensor,
    image: torch.Tensor,
    offsets: list[tuple[int, int]],
    dtype: torch.dtype,
) -> torch.Tensor:
    """The matting Laplacian's 5×5 pair weights in one pass (``MattingQuadratic.as_stencil``).

    Args:
        window_terms: ``(B, 11, H + 2, W + 2)`` float64 per-window summands, window
            ``(wy, wx)`` at ``(wy + 2, wx + 2)``, 0 around.
        image: ``(B, 3, H, W)`` float64 centred base image.
        offsets: the 12 half offsets of a 5×5 window.
        dtype: dtype of the result.

    Returns:
        ``(B, K, H, W)`` weights, 0 for pairs leaving the image.
    """
    _, kernel = _numba()
    dys, dxs = _offsets(tuple(offsets))
    b, _, h, w = image.shape
    out = torch.empty(b, len(offsets), h, w, dtype=dtype)
    args = (window_terms.contiguous().numpy(), image.contiguous().numpy(), dys, dxs, out.numpy())
    _run(kernel.matting_weights, args, b * h, b * h * w * len(offsets) * 40)
    return out


def stencil_affinity(
    features: torch.Tensor,
    offsets: list[tuple[int, int]],
    scale: float,
    semantic: torch.Tensor | None = None,
    a_l: float = 1.0,
    a_m: float = 0.0,
    mask: torch.Tensor | None = None,
    out: torch.Tensor | None = None,
    min_exponent: float = -math.inf,
) -> torch.Tensor:
    """``(a_l + a_m · s_k(i)) · exp(scale · ‖f_i − f_{i + o_k}‖²)`` for every stencil pair.

    Without ``semantic`` the factor is 1. Pairs leaving the image, or touching a pixel outside
    ``mask``, or whose exponent ``scale · ‖f_i − f_j‖²`` is below ``min_exponent``, get 0. The
    kernel writes the exponents (one pass over the offsets, no zero fill first), torch's
    vectorised ``exp`` exponentiates them in place and a second kernel applies the factor:
    about 3× faster than one ``exp`` call per pair in the kernel (measured at 512×384, stop
    25). Into ``out`` when given (``(B, K, H, W)``, the features' dtype; a non-contiguous one
    receives a copy).

    Shape:
        features ``(B, D, H, W)``, semantic ``(B, K, H, W)``, mask ``(B, 1, H, W)`` bool ->
        ``(B, K, H, W)``.
    """
    _, kernel = _numba()
    dys, dxs = _offsets(tuple(offsets))
    b, d, h, w = features.shape
    dt = features.dtype
    given = out
    if out is None or not out.is_contiguous():
        out = torch.empty(b, len(offsets), h, w, dtype=dt)
    # a mask or factor of batch 1 is broadcast, as the torch ops do (the kernels index both
    # per image); other shapes raise here, not inside the kernel
    sem = None if semantic is None else semantic.expand(out.shape).contiguous()
    m = torch.empty(0, 0, 0, 0, dtype=torch.bool)
    if mask is not None:
        m = mask.to(torch.bool).expand(b, 1, h, w).contiguous()
    np_dt = out.numpy().dtype.type
    args = (
        features.contiguous().numpy(),
        m.numpy(),
        dys,
        dxs,
        np_dt(scale),
        np_dt(min_exponent),
        out.numpy(),
    )
    _run(kernel.affinity_exponent, args, b * h, b * h * w * len(offsets) * (d + 4))
    out.exp_()  # torch's exp is vectorised (the kernel's would be libm's, one call per pair)
    if sem is not None:
        rows = b * len(offsets) * h
        args = (out.view(rows, w).numpy(), sem.view(rows, w).numpy(), np_dt(a_l), np_dt(a_m))
        _run(kernel.scale_by_factor, args, rows, rows * w * 2)
    if given is not None and given is not out:
        return given.copy_(out)
    return out
