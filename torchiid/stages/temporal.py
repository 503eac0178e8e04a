"""Stage 2's temporal term: a pull toward another frame's reflectance (video).

A :class:`~torchiid.stages.config.TemporalPrior` in the problem adds a term ``"T"`` to Eq. 12
(:func:`temporal_term`): an L1 term ``γ_T ‖c ⊙ (z − κT)‖₁`` solved by Split-Bregman like the
others (:class:`TemporalL1Term`), or a quadratic anchor ``γ_T ‖√c ⊙ (z − κT)‖²`` that enters
the ``z`` step's normal equations exactly (:class:`TemporalAnchorTerm`).
"""

from __future__ import annotations

import math

import torch

from torchiid.params import ReflectanceParameters
from torchiid.stages.config import TemporalPrior, check_group

__all__ = ["TemporalL1Term", "TemporalAnchorTerm", "temporal_term"]


class TemporalL1Term:
    """``‖diag(c) (z − T)‖₁``: an L1 pull toward a target, for Split-Bregman.

    An affine operator ``D z = c ⊙ (z − T)``: the Bregman step shrinks ``u = D z + b`` like
    the difference terms do, and the ``z`` step's right-hand side gets ``c ⊙ (d − b) + c² T``
    (from ``θ/2 ‖d − c(z − T) − b‖²``), its normal matrix ``diag(c²)``.

    Args:
        target: ``(B, C, H, W)`` the target ``T``.
        confidence: ``(B, 1, H, W)`` per-pixel weights ``c >= 0``.
    """

    def __init__(self, target: torch.Tensor, confidence: torch.Tensor) -> None:
        self.target = target.contiguous()
        self.confidence = confidence.contiguous()
        self._c2 = self.confidence.square()
        self._c2t = self._c2 * self.target

    def apply(self, z: torch.Tensor) -> torch.Tensor:
        """``c ⊙ (z − T)``, shape of ``z``."""
        return (z - self.target).mul_(self.confidence)

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """``‖c ⊙ (z − T)‖₁`` per image ``(B,)``."""
        return self.apply(z).abs_().flatten(1).sum(dim=1)

    def normal_matvec(self, z: torch.Tensor) -> torch.Tensor:
        """``c² ⊙ z`` (a fresh tensor)."""
        return self._c2 * z

    def normal_diagonal(self) -> torch.Tensor:
        """``c²``, ``(B, 1, H, W)``."""
        return self._c2

    def bregman_step(
        self, z: torch.Tensor, b: torch.Tensor | None, lam: float, with_l1: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """One Bregman update at ``z``: ``(b, rhs, ‖D z‖₁)`` (see the class notes)."""
        u = self.apply(z)
        l1 = u.abs().flatten(1).sum(dim=1) if with_l1 else None
        if b is not None:
            u += b
        b = u.clamp(-lam, lam) if b is None else b.copy_(u.clamp(-lam, lam))
        rhs = u.sub_(b, alpha=2.0).mul_(self.confidence).add_(self._c2t)
        return b, rhs, l1


class TemporalAnchorTerm:
    """``Σ c ‖z − T‖²``: a quadratic pull toward a target, in Split-Bregman's term interface.

    Quadratic, so it needs no splitting: it adds ``2γ c`` to the ``z`` step's normal matrix
    and ``2γ c T`` to its right-hand side, exactly. The solver multiplies every term's normal
    product and right-hand side by its penalty ``θ``, so this term carries
    ``coefficient = 2γ / θ``; its "L1 norm" (used for the objective as ``γ · l1``) is the
    quadratic energy ``Σ c ‖z − T‖²``.

    Args:
        target: ``(B, C, H, W)`` the target ``T``.
        confidence: ``(B, 1, H, W)`` per-pixel weights ``c >= 0``.
        coefficient: ``2γ / θ`` of the solve it enters.
    """

    def __init__(self, target: torch.Tensor, confidence: torch.Tensor, coefficient: float):
        self.target = target.contiguous()
        self.confidence = confidence.contiguous()
        self._w = self.confidence * coefficient
        self._rhs = self._w * self.target

    def l1(self, z: torch.Tensor) -> torch.Tensor:
        """The energy ``Σ c ‖z − T‖²`` per image ``(B,)`` (see the class notes)."""
        return (z - self.target).square_().mul_(self.confidence).flatten(1).sum(dim=1)

    def normal_matvec(self, z: torch.Tensor) -> torch.Tensor:
        """``(2γ/θ) c ⊙ z`` (a fresh tensor)."""
        return self._w * z

    def normal_diagonal(self) -> torch.Tensor:
        """``(2γ/θ) c``, ``(B, 1, H, W)``."""
        return self._w

    def bregman_step(
        self, z: torch.Tensor, b: torch.Tensor | None, lam: float, with_l1: bool = True
    ) -> tuple[None, torch.Tensor, torch.Tensor | None]:
        """No splitting: the state stays empty and the right-hand side is ``(2γ/θ) c T``."""
        return None, self._rhs, self.l1(z) if with_l1 else None


def temporal_term(
    prior: TemporalPrior,
    rho: torch.Tensor,
    reflectance: ReflectanceParameters,
    mask: torch.Tensor | None = None,
) -> tuple[float, TemporalL1Term | TemporalAnchorTerm] | None:
    """The temporal term ``"T"`` of a :class:`~torchiid.stages.config.TemporalPrior`.

    The target is brought to the scale of ``ρ`` on the trusted pixels (confidence > 0.5,
    inside the mask, ``Σ_c T > 1e-3``, ``Σ_c ρ > 1e-3``): with ``prior.sigma == 0`` by one
    factor per image, ``κ``, the median of ``Σ_c ρ / Σ_c T``; with ``prior.sigma > 0`` the
    target becomes ``ρ · exp(G_σ ∗ log(Σ_c T / Σ_c ρ))`` (a normalised Gaussian average over
    the trusted pixels): the other frame passes on its reflectance levels, smooth, and this
    frame's ``ρ`` its detail and edges. Its weight is ``γ_T = weight · γ_a · value_scale``
    (the data term's weight, so the term keeps its ratio to the data term along the §3.4
    schedule).

    Args:
        prior: the temporal prior.
        rho: ``(B, 3, H, W)`` the current ``ρ``.
        reflectance: the stage's parameters at this alternation (``gamma_a``,
            ``value_scale``, ``theta``).
        mask: ``(B, 1, H, W)`` bool or ``None``.

    Returns:
        ``(γ_T, term)``, or ``None`` when the weight is 0 or no pixel is trusted.
    """
    o = check_group("temporal_term", reflectance, ReflectanceParameters, "reflectance")
    gamma = prior.weight * o.gamma_a * o.value_scale
    conf = prior.confidence.to(rho.dtype).clamp(0, 1)
    if mask is not None:
        conf = conf * mask
    if not gamma > 0 or not bool((conf > 0).any()):
        return None
    target = prior.target.to(rho.dtype).clamp_min(0)
    t_sum, r_sum = target.sum(1, keepdim=True), rho.sum(1, keepdim=True)
    ok = (conf > 0.5) & (t_sum > 1e-3) & (r_sum > 1e-3)
    kappa = torch.ones(rho.shape[0], dtype=rho.dtype, device=rho.device)
    for i in range(rho.shape[0]):
        if bool(ok[i].any()):
            kappa[i] = (r_sum[i][ok[i]] / t_sum[i][ok[i]]).median()
    target = target * kappa.view(-1, 1, 1, 1)
    if prior.sigma > 0 and bool(ok.any()):
        w = ok.to(rho.dtype)
        log_ratio = (t_sum * kappa.view(-1, 1, 1, 1)).clamp_min(1e-6) / r_sum.clamp_min(1e-6)
        log_ratio = log_ratio.log_() * w
        side = 2 * int(math.ceil(3 * prior.sigma)) + 1
        side = min(side, 2 * (min(rho.shape[-2:]) // 2) - 1)
        sig = (float(prior.sigma), float(prior.sigma))
        import kornia  # on first use, as in torchiid.priors.affinity.lab_features

        num = kornia.filters.gaussian_blur2d(log_ratio, (side, side), sig, border_type="reflect")
        den = kornia.filters.gaussian_blur2d(w, (side, side), sig, border_type="reflect")
        smooth = torch.where(den > 1e-3, num / den.clamp_min(1e-6), torch.zeros_like(num))
        target = torch.where(ok, rho * smooth.exp(), target)
    if prior.norm == "l1":
        return float(gamma), TemporalL1Term(target, conf)
    coefficient = 2.0 * gamma / (o.theta * o.value_scale)
    return float(gamma), TemporalAnchorTerm(target, conf, coefficient)
