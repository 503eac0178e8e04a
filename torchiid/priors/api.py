"""The method's priors as public objects: one operator and one exact sparse matrix each.

Every prior of the method is wrapped with **one meaning** for both of its forms:

* a shading prior (``S_c`` Eq. 2, ``S_p`` Eq. 3, ``S_m`` Eq. 4, ``S_l`` Eq. 5, and ``S_s``,
  plain smoothness, which is not the paper's; on the log-shading ``s``) is the quadratic
  energy ``E(s) = sᵀ L s − 2 bᵀ s + c`` and both :meth:`ShadingPrior.matvec` and
  :meth:`ShadingPrior.to_sparse` are the **quadratic form's matrix** ``L`` (symmetric
  positive semi-definite);
* a reflectance prior (``A`` Eq. 8, ``B`` Eq. 9, ``C`` Eq. 10, on the reflectance ``z``) is the
  L1 energy ``‖W M z‖₁`` and both :meth:`ReflectancePrior.apply` and
  :meth:`ReflectancePrior.to_sparse` are the **weighted difference operator** ``W M`` (its
  normal matrix ``(W M)ᵀ (W M)`` is what the Split-Bregman ``z`` step inverts).

The wrapped terms are the very objects the solvers use (``term``): the operators are their fast
matrix-free products, the sparse matrices are assembled from the same weights.

Sparse layout. A batch is one **block-diagonal 2-D sparse COO** matrix (coalesced) over the
flat unknowns ``b·H·W + y·W + x`` -- the ordering of ``x.reshape(-1)`` for ``x`` of shape
``(B, 1, H, W)`` and the one the solvers use. 2-D COO is chosen because ``torch.sparse.mm`` (and
``@``) with a dense right-hand side is supported, with autograd for the dense operand, on CPU
and CUDA; 3-D ("hybrid batch") sparse tensors have far fewer kernels. Images of a batch share
``H·W``, so image ``b`` is the diagonal block ``[b·N:(b+1)·N, b·N:(b+1)·N]``. Ask for
``layout=torch.sparse_csr`` for faster repeated products (converted from the COO matrix).

The rows of a reflectance operator follow the layout of :meth:`ReflectancePrior.apply`:
``b·K·H·W + k·H·W + y·W + x`` for a stencil term (``K`` offsets; rows of pairs leaving the image
or the mask are empty) and ``b·P + p`` for a pair term (``P`` pairs per image). The operator acts
on one channel: ``(to_sparse() @ z[:, c].reshape(-1)).view(B, -1) ==
apply(z)[:, c].reshape(B, -1)``.

Building the priors for images needs Stage 0 and the stages' builders, which sit above this
floor: :func:`torchiid.losses.image_priors` does it with
:func:`~torchiid.stages.shading.build_shading_system` and
:func:`~torchiid.stages.reflectance.build_reflectance_terms` and wraps the result with
:func:`shading_priors` and :func:`reflectance_priors` from this module.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch

from torchiid.core.exceptions import ShapeError
from torchiid.priors.quadratic import (
    ConstraintQuadratic,
    DiagonalQuadratic,
    PairQuadratic,
    QuadraticTerm,
    StencilQuadratic,
)
from torchiid.priors.reflectance_terms import PairL1Term, StencilL1Term

__all__ = [
    "REFLECTANCE_EQUATIONS",
    "SHADING_EQUATIONS",
    "ReflectancePrior",
    "ShadingPrior",
    "reflectance_priors",
    "shading_priors",
]

SHADING_EQUATIONS: dict[str, str] = {
    "S_c": "Eq. 2 (LLE consistency of patch features)",
    "S_p": "Eq. 3 (matting-Laplacian propagation)",
    "S_m": "Eq. 4 (mid-level proposal affinity)",
    "S_l": "Eq. 5 (local Retinex)",
    "S_s": "not in the paper (plain 3x3 shading smoothness)",
}
"""Name -> the paper's equation of every shading prior (``S_s`` is not the paper's)."""

REFLECTANCE_EQUATIONS: dict[str, str] = {
    "A": "Eq. 8 (local colour affinity)",
    "B": "Eq. 9 (mid-level, colour and proposal-feature affinity)",
    "A+B": "Eqs. 8-9 merged (one term on A's pairs, exact for the L1 sum)",
    "C": "Eq. 10 (global, representative pixels)",
}
"""Name -> the paper's equation of every reflectance prior."""


def _convert(matrix: torch.Tensor, layout: torch.layout) -> torch.Tensor:
    if layout == torch.sparse_coo:
        return matrix
    if layout == torch.sparse_csr:
        return matrix.to_sparse_csr()
    raise ValueError(f"layout must be torch.sparse_coo or torch.sparse_csr, got {layout}")


def _constant(term: QuadraticTerm) -> torch.Tensor:
    """``c = Σ_r w_r c_r²`` of ``Σ_r w_r ((M x)_r − c_r)²`` per image, ``(B,)``."""
    b = term.shape[0]
    zero = torch.zeros(b, dtype=term.dtype, device=term.device)
    if isinstance(term, StencilQuadratic):
        wt = term.weighted_target
        if wt is None:
            return zero
        w = term.weights
        nz = w != 0
        c2 = torch.where(nz, wt * wt / torch.where(nz, w, torch.ones_like(w)), torch.zeros_like(w))
        return c2.flatten(1).sum(1)
    if isinstance(term, PairQuadratic):
        if term.target is None:
            return zero
        return (term.weights * term.target.square()).sum(1)
    if isinstance(term, ConstraintQuadratic):
        if term.target is None:
            return zero
        return (term.row_weights * term.target.square()).view(b, -1).sum(1)
    if isinstance(term, DiagonalQuadratic):
        if term.target is None:
            return zero
        return (term.weights * term.target.square()).flatten(1).sum(1)
    if term.rhs().abs().sum() == 0:
        return zero
    raise TypeError(f"no constant known for a {type(term).__name__} with a linear part")


@dataclass(frozen=True)
class ShadingPrior:
    """One shading prior ``E(s) = sᵀ L s − 2 bᵀ s + c = Σ_r w_r ((M s)_r − c_r)²``.

    Attributes:
        name: ``"S_c"``, ``"S_p"``, ``"S_m"``, ``"S_l"`` or ``"S_s"``.
        weight: its weight ``λ`` in Eq. 1 (at the alternation it was built for).
        term: the solver's :class:`~torchiid.priors.quadratic.QuadraticTerm` (unweighted).
        equation: the paper's equation.

    Shape:
        ``s``: ``(B, 1, H, W)`` log-shading; :meth:`to_sparse` is ``(B·H·W, B·H·W)``.
    """

    name: str
    weight: float
    term: QuadraticTerm
    equation: str = ""

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """The unknown's shape ``(B, 1, H, W)``."""
        b, c, h, w = self.term.shape
        return (b, c, h, w)

    def matvec(self, s: torch.Tensor) -> torch.Tensor:
        """``L s`` (matrix-free, the solver's product), ``(B, 1, H, W)``."""
        return self.term.matvec(s)

    def rhs(self) -> torch.Tensor:
        """The linear part ``b`` (zero except for ``S_l``'s target differences)."""
        return self.term.rhs()

    def constant(self) -> torch.Tensor:
        """The constant ``c = Σ_r w_r c_r²`` per image, ``(B,)`` (so that ``E ≥ 0``)."""
        return _constant(self.term)

    def to_sparse(self, layout: torch.layout = torch.sparse_coo) -> torch.Tensor:
        """``L`` as an exact block-diagonal sparse matrix ``(B·H·W, B·H·W)`` (see module notes)."""
        return _convert(self.term.to_sparse().coalesce(), layout)

    def energy(self, s: torch.Tensor) -> torch.Tensor:
        """``E(s)`` per image, ``(B,)``; differentiable in ``s``."""
        ls = self.term.matvec(s)
        quad = (ls * s).flatten(1).sum(1)
        lin = (self.term.rhs() * s).flatten(1).sum(1)
        return quad - 2 * lin + self.constant()


@dataclass(frozen=True)
class ReflectancePrior:
    """One reflectance sparsity prior ``‖W M z‖₁`` (summed over the channels).

    Attributes:
        name: ``"A"``, ``"B"``, ``"A+B"`` (the two merged) or ``"C"``.
        weight: its weight ``γ`` in Eq. 12 (at the alternation it was built for).
        term: the solver's :class:`~torchiid.priors.reflectance_terms.StencilL1Term` or
            :class:`~torchiid.priors.reflectance_terms.PairL1Term`.
        equation: the paper's equation.

    Shape:
        ``z``: ``(B, C, H, W)``; :meth:`apply` gives ``(B, C, K, H, W)`` (stencil term) or
        ``(B, C, P)`` (pair term); :meth:`to_sparse` is ``(B·K·H·W, B·H·W)`` or
        ``(B·P, B·H·W)``.
    """

    name: str
    weight: float
    term: StencilL1Term | PairL1Term
    equation: str = ""

    @property
    def size(self) -> tuple[int, int, int]:
        """``(B, H, W)`` of the images the prior was built for."""
        t = self.term
        if isinstance(t, StencilL1Term):
            return t.weights.shape[0], t.stencil.height, t.stencil.width
        return t.i.shape[0], t.height, t.width

    @property
    def num_rows(self) -> int:
        """Rows of the operator per image: ``K·H·W`` (stencil) or ``P`` (pairs)."""
        t = self.term
        if isinstance(t, StencilL1Term):
            return t.stencil.num_offsets * t.stencil.height * t.stencil.width
        return t.i.shape[1]

    def _check(self, z: torch.Tensor) -> None:
        b, h, w = self.size
        if z.dim() != 4 or (z.shape[0], z.shape[2], z.shape[3]) != (b, h, w):
            raise ShapeError(f"expected z of shape ({b}, C, {h}, {w}), got {tuple(z.shape)}")

    def apply(self, z: torch.Tensor) -> torch.Tensor:
        """``W M z`` (matrix-free), differentiable in ``z``."""
        self._check(z)
        return self.term.apply(z)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """``(W M)ᵀ y``, ``(B, C, H, W)``."""
        return self.term.adjoint(y)

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """``‖W M z‖₁`` per image, ``(B,)``; differentiable in ``z`` (subgradient 0 at 0)."""
        return self.apply(z).abs().flatten(1).sum(1)

    def to_sparse(self, layout: torch.layout = torch.sparse_coo) -> torch.Tensor:
        """``W M`` as an exact block-diagonal sparse matrix on one channel (module notes)."""
        t = self.term
        if isinstance(t, PairL1Term):
            return _convert(t.matrix(), layout)
        st = t.stencil
        h, w = st.height, st.width
        n = h * w
        k, i, j = st.pair_index()
        b = t.weights.shape[0]
        dev = t.weights.device
        val = t.weights[:, k, torch.div(i, w, rounding_mode="floor"), i % w]  # (B, P)
        rows = (k * n + i).view(1, -1) + (torch.arange(b, device=dev) * (st.num_offsets * n)).view(
            -1, 1
        )
        off = (torch.arange(b, device=dev) * n).view(-1, 1)
        ci, cj = (i.view(1, -1) + off).reshape(-1), (j.view(1, -1) + off).reshape(-1)
        r = rows.reshape(-1)
        idx = torch.stack([torch.cat([r, r]), torch.cat([ci, cj])])
        vals = torch.cat([val.reshape(-1), -val.reshape(-1)])
        shape = (b * st.num_offsets * n, b * n)
        m = torch.sparse_coo_tensor(idx, vals, shape, check_invariants=False).coalesce()
        return _convert(m, layout)


def shading_priors(
    terms: Mapping[str, tuple[float, QuadraticTerm]],
) -> dict[str, ShadingPrior]:
    """Wrap ``ShadingSystem.terms`` (name -> ``(λ, term)``) as :class:`ShadingPrior` objects."""
    return {
        name: ShadingPrior(name, float(lam), term, SHADING_EQUATIONS.get(name, ""))
        for name, (lam, term) in terms.items()
    }


def reflectance_priors(
    terms: Mapping[str, tuple[float, StencilL1Term | PairL1Term]],
) -> dict[str, ReflectancePrior]:
    """Wrap ``ReflectanceTerms.terms`` (name -> ``(γ, term)``) as :class:`ReflectancePrior`."""
    return {
        name: ReflectancePrior(name, float(g), term, REFLECTANCE_EQUATIONS.get(name, ""))
        for name, (g, term) in terms.items()
    }
