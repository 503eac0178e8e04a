"""The stencil L1 terms of the reflectance formulation: ``A`` and ``B`` (paper §3.3, Eqs. 8–9).

:class:`StencilL1Term` holds the pairs of an 11×11 window
(:class:`~torchiid.priors.stencil.Stencil`), weights ``(B, K, H, W)``. Its hot paths
(:meth:`~StencilL1Term.normal_matvec`, :meth:`~StencilL1Term.bregman_step`) loop over the ``K``
offsets with slices and never materialise the ``(B, C, K, H, W)`` differences; on the CPU the
compiled kernels run them in one pass (:mod:`torchiid.priors.kernels`).

The colour features and affinities that weigh the pairs (:mod:`torchiid.priors.affinity`) and
the other L1 terms (:mod:`torchiid.priors.l1_terms`) are importable from here too.

Masks: a ``(B, 1, H, W)`` bool ``mask`` zeroes every pair touching a pixel outside it, so those
pixels keep only the data term; the solver then returns ``ρ`` there.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property

import torch

from torchiid.core.exceptions import ParameterError
from torchiid.priors import kernels
from torchiid.priors.affinity import (
    COLOUR_WEIGHTS,
    MIN_EXPONENT,
    lab_features,
    merged_stencil_affinity,
    pair_affinity,
    stencil_affinity,
)
from torchiid.priors.l1_terms import (
    BregmanStats,
    L1Term,
    MeasuredStep,
    PairL1Term,
    Step,
    data_term,
)
from torchiid.priors.stencil import Stencil, shift_slices

__all__ = [
    "COLOUR_WEIGHTS",
    "lab_features",
    "stencil_affinity",
    "merged_stencil_affinity",
    "pair_affinity",
    "StencilL1Term",
    "PairL1Term",
    "BregmanStats",
    "REPLAY_STEPS",
    "MIN_EXPONENT",
    "data_term",
]


def _sums(x: torch.Tensor) -> torch.Tensor:
    return x.flatten(1).sum(dim=1)


#: earlier updates a replayed Bregman state (:meth:`StencilL1Term.bregman_step`) recomputes
#: at most; a solve with more stores its state from then on
REPLAY_STEPS = 3


@dataclass(frozen=True)
class _Replay:
    """A Bregman state kept as the ``z`` of its updates (oldest first) and their ``λ``."""

    history: list[torch.Tensor]
    lam: float


class StencilL1Term(L1Term):
    """``diag(v) M`` over a stencil's pairs, weights ``(B, K, H, W)`` (``A``, ``B``: Eqs. 8, 9).

    Args:
        stencil: the fixed-offset pairs.
        weights: pair weights ``v`` indexed by the first pixel; entries of pairs leaving the
            image are ignored (set to 0).
        zero_invalid: set those entries to 0 (a copy); ``False`` when they already are, as for
            :func:`stencil_affinity` and :func:`merged_stencil_affinity`, saves a pass.
        state: optional storage ``(B, C, K, H, W)`` for the Bregman variable of a solve that
            starts from the zero state (its contents are overwritten, never read); reusing one
            buffer across solves avoids faulting in fresh memory every time.
        warm: ``state`` holds a Bregman variable to start from (e.g. the previous solve's on
            the same image; entries of pairs leaving the image are never read): Split-Bregman
            then starts with the update ``b ← clamp(W M z + b, −λ, λ)`` from it instead of from
            the zero state (:attr:`initial_state`).
        keep_state: store the Bregman variable at every update, also the last one of a
            solve (needed when ``state`` is to warm-start a later solve). ``False``: the last
            update (``final=True``) leaves it unwritten, saving a write of ``C·K`` planes
            (141 MB in float32 at 512×384); :attr:`state_written` then tells that the storage
            is stale.
        replay: with ``keep_state=False``, keep the state as the ``z`` of its updates instead
            of storing it (see :meth:`bregman_step`); ``False`` for solves that make more
            than ``REPLAY_STEPS + 1`` updates, which would replay at a loss.
        state_step: with a ``torch.int16`` ``state`` and ``warm``, the step of its values
            (:attr:`state_step` of the solve that wrote it).

    Fixed-point state. A ``torch.int16`` ``state`` keeps the Bregman variable in 16-bit fixed
    point: each value of ``[−λ, λ]`` as an integer ``q`` in ``[−32767, 32767]``, read back as
    ``q · state_step`` with ``state_step = λ / 32767`` of the update that wrote it
    (:func:`~torchiid.priors.kernels.fixed_point_scales`; at most ``λ / 65534`` off). Half the
    memory and memory traffic of float32, for long solves (the ``converged`` preset's
    pipeline cache uses it). Each update computes in the image's dtype and rounds only what it
    stores; the compiled kernel and the torch ops round the same way, so they agree bitwise.
    """

    def __init__(
        self,
        stencil: Stencil,
        weights: torch.Tensor,
        *,
        zero_invalid: bool = True,
        state: torch.Tensor | None = None,
        warm: bool = False,
        keep_state: bool = True,
        replay: bool = True,
        state_step: float | None = None,
    ) -> None:
        if warm and state is None:
            raise ParameterError(
                "StencilL1Term(warm=True) needs state=, the Bregman variable to start from"
            )
        if state is not None and state.dtype == torch.int16:
            if warm and not (state_step is not None and state_step > 0):
                raise ParameterError(
                    "StencilL1Term(warm=True) with an int16 state needs state_step=, the step "
                    "of its values (the state_step of the solve that wrote it)"
                )
        elif state is not None and not state.is_floating_point():
            raise ParameterError(f"state must be floating point or torch.int16, got {state.dtype}")
        self.stencil = stencil
        if zero_invalid:
            weights = weights * stencil.valid.to(device=weights.device, dtype=weights.dtype)
        self.weights = weights
        self.state = state
        self.warm = warm
        self.keep_state = keep_state
        self.replay = replay
        self.state_written = False  # the last update stored its Bregman variable
        self.state_step = state_step  # the step of an int16 state's values

    @property
    def skips_final_state(self) -> bool:
        """Whether Split-Bregman may call the solve's last update with ``final=True``."""
        return not self.keep_state

    @property
    def initial_state(self) -> torch.Tensor | None:
        """The Bregman variable Split-Bregman starts from (``None``: the zero state)."""
        return self.state if self.warm else None

    def init_state(self, z: torch.Tensor) -> torch.Tensor:
        """Zero Bregman variable ``(B, C, K, H, W)``."""
        b, c, h, w = z.shape
        return z.new_zeros(b, c, self.stencil.num_offsets, h, w)

    def apply(self, z: torch.Tensor) -> torch.Tensor:
        """``diag(v) M z``: ``(B, C, H, W) -> (B, C, K, H, W)`` (materialises; for reference)."""
        return self.weights.unsqueeze(1) * self.stencil.apply(z)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``Mᵀ diag(v) y``: ``(B, C, K, H, W) -> (B, C, H, W)``."""
        return self.stencil.adjoint(self.weights.unsqueeze(1) * y)

    def _loop(self) -> Iterator[tuple[int, tuple[slice, slice, slice, slice]]]:
        h, w = self.stencil.height, self.stencil.width
        for k, (dy, dx) in enumerate(self.stencil.offsets):
            yield k, shift_slices(dy, dx, h, w)

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """``‖diag(v) M z‖₁`` per image ``(B,)`` without materialising ``M z``."""
        out = z.new_zeros(z.shape[0])
        for k, (yi, xi, yj, xj) in self._loop():
            d = (z[:, :, yi, xi] - z[:, :, yj, xj]).abs_().mul_(self.weights[:, k : k + 1, yi, xi])
            out += d.flatten(1).sum(dim=1)
        return out

    @cached_property
    def _degree(self) -> torch.Tensor:
        """Weighted degree ``Σ_j v²_ij`` over both directions of every pair, ``(B, 1, H, W)``."""
        if kernels.usable(self.weights, offsets=self.stencil.offsets):
            return kernels.stencil_degree(self.weights, self.stencil.offsets, square=True)
        return self.stencil.laplacian_diagonal(self.weights.square(), zero_invalid=False)

    @cached_property
    def _w2(self) -> torch.Tensor:
        """The squared weights ``v²`` (only the torch product keeps them)."""
        return self.weights.square()

    def normal_matvec(self, z: torch.Tensor) -> torch.Tensor:
        """``Mᵀ diag(v²) M z = deg ⊙ z − Σ_k v²_k ⊙ (shift_k(z) + shift_−k(z))``.

        Two fused in-place ``addcmul`` per offset, both reading the weight stored at the first
        pixel of the pair, so nothing of size ``(B, K, H, W)`` is built per call. On CPU
        tensors outside autograd the compiled one-pass kernel computes the same product, the
        weights squared on the fly (:func:`torchiid.priors.kernels.stencil_product`).

        Shape:
            ``(B, C, H, W) -> (B, C, H, W)``.
        """
        same_batch = z.shape[0] == self.weights.shape[0]  # else the torch ops broadcast
        if same_batch and kernels.usable(z, self.weights, offsets=self.stencil.offsets):
            return kernels.stencil_product(z, self.weights, self.stencil.offsets, square=True)
        out = self._degree * z
        for k, (yi, xi, yj, xj) in self._loop():
            wk = self._w2[:, k : k + 1, yi, xi]
            out[:, :, yi, xi].addcmul_(z[:, :, yj, xj], wk, value=-1)
            out[:, :, yj, xj].addcmul_(z[:, :, yi, xi], wk, value=-1)
        return out

    def normal_diagonal(self) -> torch.Tensor:
        """Diagonal of ``Mᵀ diag(v²) M`` (the weighted degree), ``(B, 1, H, W)``."""
        return self._degree

    def bregman_step(
        self,
        z: torch.Tensor,
        b: torch.Tensor | _Replay | None,
        lam: float,
        with_l1: bool = True,
        *,
        final: bool = False,
        stats: bool = False,
    ) -> Step | MeasuredStep:
        """Fused per-offset version of :meth:`L1Term.bregman_step` (``b`` updated in place).

        The differences of each offset are written into one scratch buffer, so the loop
        allocates nothing; ``with_l1=False`` skips the objective's reduction (about a third of
        the time). With ``b=None`` (the zero state) the new state is allocated uninitialised:
        its entries for pairs leaving the image are unspecified and never read. With
        ``final=True`` and ``keep_state=False`` the new state is not stored: the clamped
        values go through a second scratch buffer and ``b`` is returned unchanged (``None``
        from the zero state).

        Replayed state. With ``keep_state=False`` on CPU (the compiled kernels, see
        :func:`~torchiid.priors.kernels.bregman_replay`) and ``with_l1=False``, a solve from
        the zero state keeps no ``(B, C, K, H, W)`` variable at all: the state passed between
        the calls is the list of the ``z`` it was updated at, and each update rebuilds every
        pair's variable from them, in the torch path's operations and order. Up to
        :data:`REPLAY_STEPS` earlier updates are replayed; a longer solve (or a call that
        needs the torch path) stores the state from then on. At the ``default`` preset's two
        updates per solve this saves writing and reading ``C·K`` planes per alternation.

        Stored state. Otherwise, on the same compiled path, the update reads and writes the
        stored state in one pass (:func:`~torchiid.priors.kernels.bregman_update`; the torch
        ops, kept for GPUs, autograd and ``with_l1=True``, make about ten per offset). A
        ``torch.int16`` state (see the class notes) halves what that pass moves.

        ``stats=True`` also returns the update's :class:`BregmanStats` (a fourth item), from
        the same pass on the compiled path (``kernels.bregman_update(stats=True)``).
        """
        same_batch = z.shape[0] == self.weights.shape[0]
        compiled = (
            not with_l1
            and same_batch
            and kernels.usable(z, self.weights, offsets=self.stencil.offsets)
        )
        if compiled and not self.keep_state and self.replay and not stats:
            replayed = self._replayed_step(z, b, lam, final)
            if replayed is not None:
                return replayed
        if isinstance(b, _Replay):
            b = self._materialise(b, compiled)
        state_ok = b is None or (
            b.is_contiguous()
            and (kernels.usable(z, b) or (b.dtype == torch.int16 and b.device.type == "cpu"))
        )
        if not (compiled and state_ok):
            step = self._torch_step(z, b, lam, (with_l1, final), stats=stats)
            return step[:3] if step[3] is None else (step[0], step[1], step[3].l1, step[3])
        # the stored state in one compiled pass (the torch path makes ~10 per offset)
        store = not (final and not self.keep_state)
        self.state_written = store
        fresh = b is None
        if store and fresh:
            b = self._state_storage(z)
        out = kernels.bregman_update(
            z, self.weights, self.stencil.offsets, lam, state=b, read=not fresh,
            write=store, state_step=self.state_step or 1.0, stats=stats,
        )  # fmt: skip
        if store and b is not None and b.dtype == torch.int16:
            self.state_step = kernels.fixed_point_scales(lam)[0]
        if isinstance(out, torch.Tensor):
            return b, out, None
        rhs, adj, sums = out
        s = sums.to(z.dtype).unbind(1)
        return b, rhs, s[0], BregmanStats(s[0], s[1], s[2], s[3], adj)

    def _replayed_step(
        self, z: torch.Tensor, b: torch.Tensor | _Replay | None, lam: float, final: bool
    ) -> Step | None:
        """The update of a state kept as its history, or ``None`` where it has to be stored."""
        if isinstance(b, torch.Tensor):
            return None
        history = [] if b is None else b.history
        if len(history) > REPLAY_STEPS or (b is not None and b.lam != lam):
            return None
        self.state_written = False
        rhs = kernels.bregman_replay(history, z, self.weights, self.stencil.offsets, lam)
        if final:
            return b, rhs, None
        return _Replay([*history, z.clone()], lam), rhs, None

    def rescale_state(
        self, b: torch.Tensor | _Replay | None, lam: float, new_lam: float
    ) -> torch.Tensor | None:
        """:meth:`L1Term.rescale_state`; an int16 state only changes its step (no pass)."""
        if isinstance(b, _Replay):
            compiled = kernels.usable(b.history[-1], self.weights, offsets=self.stencil.offsets)
            b = self._materialise(b, compiled)
        if b is not None and b.dtype == torch.int16:
            # q = b / λ · 32767 is the dual variable: read it with the step of the new λ
            self.state_step = kernels.fixed_point_scales(new_lam)[0]
            return b
        return super().rescale_state(b, lam, new_lam)

    def _state_storage(self, z: torch.Tensor) -> torch.Tensor:
        """Storage ``(B, C, K, H, W)`` for a fresh state: ``state`` when it fits, else new."""
        bsz, c, h, w = z.shape
        shape = (bsz, c, self.stencil.num_offsets, h, w)
        st = self.state
        if st is not None and st.shape == shape and st.device == z.device:
            if st.dtype in (z.dtype, torch.int16):
                return st
        return z.new_empty(shape)

    def _materialise(self, replay: _Replay, compiled: bool) -> torch.Tensor:
        """The stored Bregman variable of a replayed state (its updates run again)."""
        *earlier, last = replay.history
        storage = self._state_storage(last)
        fixed = storage.dtype == torch.int16
        if fixed:  # replayed in the image's dtype, like the kernel, and rounded once
            self.state_step = kernels.fixed_point_scales(replay.lam)[0]
        if compiled:
            kernels.bregman_update(
                last, self.weights, self.stencil.offsets, replay.lam,
                state=storage, write=True, history=earlier,
            )  # fmt: skip
            return storage
        b = None
        for zs in replay.history:
            b = self._torch_step(zs, b, replay.lam, (False, False), float_state=fixed)[0]
        if b is None:  # the loop stores every update: never
            raise RuntimeError("a replayed Bregman state without updates")
        if fixed:
            storage.copy_(b.mul_(kernels.fixed_point_scales(replay.lam)[1]).round_())
            return storage
        return b

    def _torch_step(
        self,
        z: torch.Tensor,
        b: torch.Tensor | None,
        lam: float,
        flags: tuple[bool, bool],
        float_state: bool = False,
        stats: bool = False,
    ) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor | None, BregmanStats | None]:
        """The update in torch ops; ``flags``: ``(with_l1, final)``.

        Returns the state, the right-hand side, ``‖W M z‖₁`` and the stats (``None`` unless
        asked for).
        """
        with_l1, final = flags
        rhs = torch.zeros_like(z)
        scratch = torch.empty_like(z)
        l1 = z.new_zeros(z.shape[0]) if with_l1 or stats else None
        sums = z.new_zeros(3 if stats else 0, z.shape[0])  # ‖b' − b‖², ‖W M z‖², ‖d‖²
        adj = torch.zeros_like(z) if stats else None
        prior = b  # the state the update reads (None: the zero state)
        store = not (final and not self.keep_state)
        self.state_written = store
        if b is None and store:
            b = z.new_empty(self.init_state(z).shape) if float_state else self._state_storage(z)
        dest = b if store else None  # where the new state goes
        scales = (
            kernels.fixed_point_scales(lam) if b is not None and b.dtype == torch.int16 else None
        )
        step_in = self.state_step or 1.0
        # the clamped values where they are not written into the state (else unused)
        clamped = torch.empty_like(z) if dest is None or scales is not None else scratch
        for k, (yi, xi, yj, xj) in self._loop():
            wk = self.weights[:, k : k + 1, yi, xi]
            u = torch.sub(z[:, :, yi, xi], z[:, :, yj, xj], out=scratch[:, :, yi, xi]).mul_(wk)
            if l1 is not None:
                l1 += u.abs().flatten(1).sum(dim=1)
            if stats:
                sums[1] += _sums(u.square())
            old = None
            if prior is not None:
                bk = prior[:, :, k, yi, xi]
                old = bk.to(z.dtype).mul_(step_in) if scales is not None else bk
                if stats and old is bk:
                    old = bk.clone()  # the new b overwrites it
                u += old
            # the new b, written straight into the state (or into scratch when not kept or
            # stored in fixed point)
            bk = (
                dest[:, :, k, yi, xi]
                if dest is not None and scales is None
                else clamped[:, :, yi, xi]
            )
            torch.clamp(u, -lam, lam, out=bk)
            if adj is not None:
                sums[0] += _sums(bk.square() if old is None else (bk - old).square_())
                sums[2] += _sums((u - bk).square_())
                adj[:, :, yi, xi].addcmul_(bk, wk)
                adj[:, :, yj, xj].addcmul_(bk, wk, value=-1)
            if dest is not None and scales is not None:
                dest[:, :, k, yi, xi] = bk.mul(scales[1]).round_()
            e = u.sub_(bk, alpha=2.0)  # d - b; (W M)^T scatters w * (d - b) to i and j
            rhs[:, :, yi, xi].addcmul_(e, wk)
            rhs[:, :, yj, xj].addcmul_(e, wk, value=-1)
        if dest is not None and scales is not None:
            self.state_step = scales[0]
        if adj is None or l1 is None:
            return b, rhs, l1, None
        return b, rhs, l1, BregmanStats(l1, sums[0], sums[1], sums[2], adj)

    def matrix(self) -> torch.Tensor:
        """``diag(v) M`` as sparse COO ``(B·P, B·H·W)`` acting on one channel."""
        return self.stencil.difference_matrix(self.weights.square())
