"""Sparse quadratic energies ``E(x) = x^T A x - 2 b^T x + const`` over a one-channel image.

Every shading prior of the paper (Eq. 1-5) is a sum of squared, weighted linear residuals
``E(x) = sum_r w_r ((M x)_r - c_r)^2`` with a difference or constraint operator ``M``, so
``A = M^T W M`` is symmetric positive semi-definite by construction and ``b = M^T W c``
(:class:`~torchiid.priors.quadratic_term.QuadraticTerm`). This module holds the stencil term
:class:`StencilQuadratic` and the weighted sum :class:`SumQuadratic`; the terms over explicit
rows (:mod:`torchiid.priors.row_quadratics`) and the base class are importable from here too.

The unknown ``x`` is ``(B, 1, H, W)``; a batch is the block-diagonal system on ``B * H * W``
unknowns, flat index ``b * H * W + y * W + x``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors import kernels
from torchiid.priors.quadratic_term import QuadraticTerm, sparse_gram
from torchiid.priors.row_quadratics import ConstraintQuadratic, DiagonalQuadratic, PairQuadratic
from torchiid.priors.stencil import Stencil, shift_slices

#: both directions of every pair: ``(slices, weight view)``, the weights ``(B, 2K, H, W)`` and
#: the degree ``(B, 1, H, W)``
_Directed = tuple[
    list[tuple[tuple[slice, slice, slice, slice], torch.Tensor]], torch.Tensor, torch.Tensor
]

__all__ = [
    "QuadraticTerm",
    "StencilQuadratic",
    "PairQuadratic",
    "ConstraintQuadratic",
    "DiagonalQuadratic",
    "SumQuadratic",
    "sparse_gram",
]


class StencilQuadratic(QuadraticTerm):
    """``sum_k w_k (x_i - x_{i+o_k} - c_k)^2`` over the pairs of a :class:`Stencil`.

    Args:
        stencil: the fixed-offset neighbourhood.
        weights: ``(B, K, H, W)`` pair weights (invalid pairs are ignored). Normally
            non-negative; signed weights are allowed when the sum stays PSD (the matting
            Laplacian's stencil form), ``to_sparse`` handles both.
        target: optional ``(B, K, H, W)`` target differences ``c`` (e.g. ``log p_i - log p_j``
            of the Retinex term, Eq. 5); ``None`` means 0.
        zero_invalid: set the weights of pairs leaving the image to 0 (a copy); ``False``
            when they already are (the compiled builders write 0 there), saving a pass.
    """

    def __init__(
        self,
        stencil: Stencil,
        weights: torch.Tensor,
        target: torch.Tensor | None = None,
        zero_invalid: bool = True,
    ) -> None:
        b, k, h, w = weights.shape
        if (k, h, w) != (stencil.num_offsets, stencil.height, stencil.width):
            raise ShapeError(
                f"expected weights (B, {stencil.num_offsets}, {stencil.height}, "
                f"{stencil.width}), got {tuple(weights.shape)}"
            )
        if target is not None and target.shape != weights.shape:
            raise ShapeError(
                f"target {tuple(target.shape)} must match weights {tuple(weights.shape)}"
            )
        self.stencil = stencil
        if zero_invalid:
            weights = weights * stencil.valid.to(device=weights.device, dtype=weights.dtype)
        self.weights = weights
        self.weighted_target = None if target is None else self.weights * target
        self.shape = (b, 1, h, w)
        self.dtype = weights.dtype
        self.device = weights.device

    def _directed(self) -> _Directed:
        """Both pair directions: ``(slices, weight view)`` each, weights ``(B, 2K, H, W)``, degree.

        Cached for the current ``weights`` tensor (recomputed when it is replaced, e.g. by
        :class:`SumQuadratic` merging terms).
        """
        cache: tuple[torch.Tensor, _Directed] | None = self.__dict__.get("_directed_cache")
        if cache is not None and cache[0] is self.weights:
            return cache[1]
        b, k_, h, w = self.weights.shape
        wf = self.weights.new_zeros(b, 2 * k_, h, w)
        wf[:, :k_] = self.weights
        slices = []
        for k, (dy, dx) in enumerate(self.stencil.offsets):
            yi, xi, yj, xj = shift_slices(dy, dx, h, w)
            wf[:, k_ + k, yj, xj] = self.weights[:, k, yi, xi]
            slices.append((yi, xi, yj, xj))
        slices += [(yj, xj, yi, xi) for yi, xi, yj, xj in slices]
        # the weight operand of every product, sliced once (views, no copies)
        wviews = [wf[:, k : k + 1, yi, xi] for k, (yi, xi, _, _) in enumerate(slices)]
        out = (list(zip(slices, wviews, strict=True)), wf, wf.sum(dim=1, keepdim=True))
        self.__dict__["_directed_cache"] = (self.weights, out)
        return out

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``M^T W M x = deg * x - sum_o w_o * shift_o(x)`` with shifted slices.

        One fused ``addcmul`` per direction of each offset (``2K`` in all) on cached
        per-direction weights; no sparse matrix, no ``(B, K, H, W)`` temporaries. On CPU
        tensors outside autograd the compiled one-pass kernel computes the same product
        (:func:`torchiid.priors.kernels.stencil_product`).
        """
        self._check(x)
        if kernels.usable(x, self.weights, offsets=self.stencil.offsets):
            return kernels.stencil_product(x, self.weights, self.stencil.offsets)
        ops, _, deg = self._directed()
        out = deg * x
        for (yi, xi, yj, xj), wk in ops:
            out[:, :, yi, xi].addcmul_(x[:, :, yj, xj], wk, value=-1)
        return out

    def diagonal(self) -> torch.Tensor:
        """``diag(A)``: each pixel's summed pair weights."""
        # the weights of pairs leaving the image are 0 (the constructor's invariant)
        if kernels.usable(self.weights, offsets=self.stencil.offsets):
            return kernels.stencil_degree(self.weights, self.stencil.offsets, square=False)
        return self.stencil.laplacian_diagonal(self.weights, zero_invalid=False)

    def rhs(self) -> torch.Tensor:
        """``M^T W c``."""
        if self.weighted_target is None:
            return super().rhs()
        return self.stencil.adjoint(self.weighted_target.unsqueeze(1), zero_invalid=False)

    def to_sparse(self) -> torch.Tensor:
        """``M^T W M`` assembled from :meth:`Stencil.pair_index` (weights may be signed)."""
        k, i, j = self.stencil.pair_index()
        b, n = self.shape[0], self.shape[2] * self.shape[3]
        wv = self.weights[:, k, i // self.shape[3], i % self.shape[3]].reshape(-1)  # (B * P,)
        off = (torch.arange(b, device=self.device) * n).view(-1, 1)
        gi = (i.view(1, -1) + off).reshape(-1)
        gj = (j.view(1, -1) + off).reshape(-1)
        idx = torch.stack([torch.cat([gi, gj, gi, gj]), torch.cat([gi, gj, gj, gi])])
        val = torch.cat([wv, wv, -wv, -wv])
        return torch.sparse_coo_tensor(idx, val, (b * n, b * n), check_invariants=False).coalesce()

    def embedded(self, stencil: Stencil) -> StencilQuadratic:
        """The same term on a larger stencil whose offsets include this one's."""
        pos = {o: n for n, o in enumerate(stencil.offsets)}
        if (
            stencil.height != self.stencil.height
            or stencil.width != self.stencil.width
            or any(o not in pos for o in self.stencil.offsets)
        ):
            raise ShapeError("the target stencil does not contain this term's offsets")
        b, _, h, w = self.weights.shape
        sel = torch.tensor([pos[o] for o in self.stencil.offsets], device=self.device)
        wts = self.weights.new_zeros(b, stencil.num_offsets, h, w)
        wts[:, sel] = self.weights
        out = StencilQuadratic(stencil, wts)
        if self.weighted_target is not None:
            wt = self.weights.new_zeros(b, stencil.num_offsets, h, w)
            wt[:, sel] = self.weighted_target
            out.weighted_target = wt
        return out

    def scaled(self, factor: float) -> StencilQuadratic:
        """This term times ``factor >= 0`` (same stencil, scaled weights)."""
        out = StencilQuadratic.__new__(StencilQuadratic)
        out.__dict__.update(self.__dict__)
        out.__dict__.pop("_directed_cache", None)
        out.weights = self.weights * factor
        out.weighted_target = (
            None if self.weighted_target is None else self.weighted_target * factor
        )
        return out


class SumQuadratic(QuadraticTerm):
    """``sum_t lambda_t E_t``: a weighted sum of terms on the same unknowns.

    Terms given as ``None`` or with weight 0 are dropped. Stencil terms whose offsets all
    belong to the widest stencil among them (e.g. 3x3 terms and a 5x5 matting stencil) are
    merged into one term on it (one shifted product instead of several).

    Args:
        terms: ``(weight, term)`` pairs.

    Raises:
        ShapeError: terms on different unknown shapes, or no active term.
    """

    def __init__(self, terms: Sequence[tuple[float, QuadraticTerm | None]]) -> None:
        active = [(float(lam), t) for lam, t in terms if t is not None and float(lam) != 0.0]
        if not active:
            raise ShapeError("SumQuadratic needs at least one term with a non-zero weight")
        shapes = {tuple(t.shape) for _, t in active}
        if len(shapes) != 1:
            raise ShapeError(f"terms act on different unknown shapes: {sorted(shapes)}")
        merged: dict[int, StencilQuadratic] = {}
        others: list[tuple[float, QuadraticTerm]] = []
        stencils = [t.stencil for _, t in active if isinstance(t, StencilQuadratic)]
        widest = max(stencils, key=lambda s: s.num_offsets) if stencils else None
        for lam, t in active:
            if not isinstance(t, StencilQuadratic):
                others.append((lam, t))
                continue
            # accumulate lam * t, offset by offset, into one term on the widest stencil
            # (or on t's own when it does not fit): one buffer per stencil, no per-term copies
            fits = widest is not None and set(t.stencil.offsets) <= set(widest.offsets)
            st = widest if widest is not None and fits else t.stencil
            m = merged.get(id(st))
            if m is None:
                m = StencilQuadratic.__new__(StencilQuadratic)
                m.stencil, m.shape, m.dtype, m.device = st, t.shape, t.dtype, t.device
                m.weights = t.weights.new_zeros(t.shape[0], st.num_offsets, *t.shape[2:])
                m.weighted_target = None
                merged[id(st)] = m
            pairs = [(m.weights, t.weights)]
            if t.weighted_target is not None:
                if m.weighted_target is None:
                    m.weighted_target = torch.zeros_like(m.weights)
                pairs.append((m.weighted_target, t.weighted_target))
            for dst, src in pairs:
                if st is t.stencil:
                    dst.add_(src, alpha=lam)
                    continue
                pos = {o: n for n, o in enumerate(st.offsets)}
                for n, o in enumerate(t.stencil.offsets):
                    dst[:, pos[o]].add_(src[:, n], alpha=lam)
        self.terms: list[tuple[float, QuadraticTerm]] = [(1.0, m) for m in merged.values()] + others
        first = active[0][1]
        b, c, h, w = first.shape
        self.shape = (b, c, h, w)
        self.dtype = first.dtype
        self.device = first.device

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """``sum_t lambda_t A_t x``."""
        out: torch.Tensor | None = None
        for lam, t in self.terms:
            if out is not None and isinstance(t, ConstraintQuadratic):
                t.add_matvec(x, out, lam)  # into the stencil's fresh product, no HxW temporary
                continue
            y = t.matvec(x)
            if out is None:
                out = y if lam == 1.0 else lam * y
            else:
                out = out.add_(y, alpha=lam)  # out is a fresh tensor of this call
        return _nonempty(out)

    def diagonal(self) -> torch.Tensor:
        """``sum_t lambda_t diag(A_t)``."""
        return self._weighted(lambda t: t.diagonal())

    def rhs(self) -> torch.Tensor:
        """``sum_t lambda_t b_t``."""
        return self._weighted(lambda t: t.rhs())

    def _weighted(self, part: Callable[[QuadraticTerm], torch.Tensor]) -> torch.Tensor:
        """``sum_t lambda_t part(t)``, summed as Python's ``sum`` does (from 0)."""
        out: torch.Tensor | None = None
        for lam, t in self.terms:
            v = lam * part(t)
            out = 0 + v if out is None else out + v
        return _nonempty(out)

    def to_sparse(self) -> torch.Tensor:
        """``sum_t lambda_t A_t`` assembled."""
        out: torch.Tensor | None = None
        for lam, t in self.terms:
            a = t.to_sparse() * lam
            out = a if out is None else out + a
        return _nonempty(out).coalesce()


def _nonempty(total: torch.Tensor | None) -> torch.Tensor:
    """The sum over the terms (a :class:`SumQuadratic` has at least one)."""
    if total is None:
        raise ShapeError("SumQuadratic needs at least one term with a non-zero weight")
    return total
