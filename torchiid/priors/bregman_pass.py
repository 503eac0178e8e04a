"""``StencilL1Term``'s Bregman update in one compiled pass, and its 16-bit fixed-point state.

The torch ops make about ten passes over the ``(B, C, K, H, W)`` Bregman variable per offset;
the kernel (:mod:`torchiid.priors.bregman_kernels`) reads and writes it once, or not at all
when the state is replayed from the ``z`` of the earlier updates. A ``torch.int16`` state
holds the variable in 16-bit fixed point (:func:`fixed_point_scales`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

import numpy as np
import torch

from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.priors.kernel_runtime import bands, kernel_module, offset_arrays, run_bands

if TYPE_CHECKING:
    from collections.abc import Sequence

__all__ = [
    "bregman_replay",
    "bregman_update",
    "fixed_point_scales",
    "fixed_point_fits",
    "STATE_LEVELS",
    "REPLAY_BLOCK_ROWS",
]

#: the largest magnitude of a 16-bit fixed-point Bregman variable: ``λ`` is stored as this
STATE_LEVELS = 32767

#: rows per block of :func:`bregman_update` (fixed, so that the result does not depend on
#: the thread count)
REPLAY_BLOCK_ROWS = 32


def bregman_replay(
    history: Sequence[torch.Tensor],
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
    # without stats: the right-hand side only
    return cast(torch.Tensor, bregman_update(z, weights, offsets, lam, history=history))


def bregman_update(
    z: torch.Tensor,
    weights: torch.Tensor,
    offsets: list[tuple[int, int]],
    lam: float,
    *,
    state: torch.Tensor | None = None,
    read: bool = False,
    write: bool = False,
    history: Sequence[torch.Tensor] = (),
    state_step: float = 1.0,
    stats: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A ``StencilL1Term`` Bregman update at ``z``: its right-hand side, ``state`` updated.

    Every pair's Bregman variable starts from ``state`` (``read``) or from 0, is replayed
    through the updates at the ``z`` in ``history`` (oldest first), is updated at ``z`` and
    written back to ``state`` (``write``); returns ``Σ_k (W M)ᵀ (d_k − b_k)`` (see
    ``bregman_kernels._bregman_update``). The rows are cut into blocks of
    :data:`REPLAY_BLOCK_ROWS`, run in runs of whole blocks on torch's thread count; each
    block's contributions to the rows after it are added once all blocks are done, in block
    order, so the result does not depend on the number of threads.

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
    kernel = kernel_module()
    dys, dxs = offset_arrays(tuple(offsets))
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
    dtype = rhs.numpy().dtype
    fixed = st.dtype == torch.int16
    scale_in = dtype.type(state_step if fixed else 1.0)
    inv_out = dtype.type(fixed_point_scales(lam)[1] if fixed else 0.0)
    depth = max(1, int(dys.max()))
    rows = b * h
    blocks = -(-rows // REPLAY_BLOCK_ROWS)
    work = rows * w * len(offsets) * c * (4 + 3 * len(history))
    halo = np.empty((blocks, depth, c, w), dtype=dtype)
    # the measured update's outputs, or empty arrays (the kernel leaves them alone)
    adj = torch.empty_like(rhs) if stats else torch.empty(0, 0, 0, 0, dtype=z.dtype)
    halo2 = np.empty_like(halo) if stats else np.empty((0, 0, 0, 0), dtype=dtype)
    sums = np.empty((blocks if stats else 0, b, 4), dtype=np.float64)
    args = (
        zs.numpy(),
        weights.contiguous().numpy(),
        (dys, dxs),
        st.numpy(),
        (dtype.type(lam), bool(read), bool(write), scale_in, inv_out),
        (rhs.numpy(), halo),
        (adj.numpy(), halo2, sums),
        REPLAY_BLOCK_ROWS,
    )
    run_bands(kernel.bregman_update, args, bands(blocks, work))
    kernel.add_halos(rhs.numpy(), halo, REPLAY_BLOCK_ROWS)
    if not stats:
        return rhs
    kernel.add_halos(adj.numpy(), halo2, REPLAY_BLOCK_ROWS)
    return rhs, adj, torch.from_numpy(sums.sum(axis=0))


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
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        step = np.float32(lam / STATE_LEVELS) if lam > 0 else np.float32(0)
        inverse = np.float32(STATE_LEVELS / lam) if lam > 0 else np.float32(np.inf)
    tiny = np.finfo(np.float32).tiny
    if not (step >= tiny and np.isfinite(step) and np.isfinite(inverse)):
        return None
    return float(step), float(inverse)
