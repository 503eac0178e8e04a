"""The multigrid smoother: Chebyshev polynomials in ``D^{-1} A`` and their eigenvalue bound."""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["lanczos_lmax", "chebyshev"]

Operator = Callable[[torch.Tensor], torch.Tensor]


def lanczos_lmax(
    matvec: Operator,
    dinv: torch.Tensor,
    iters: int,
    seed: int = 0,
) -> torch.Tensor:
    """Per-item estimate ``(B, 1, 1, 1)`` of the largest eigenvalue of ``D^{-1} A``.

    ``iters`` Lanczos steps on the symmetric ``D^{-1/2} A D^{-1/2}`` (same spectrum) from a
    zero-mean random start; the estimate is the largest eigenvalue of the Lanczos
    tridiagonal, which never exceeds the true one (callers add a margin). Lanczos rather than
    a power iteration: where the top of the spectrum is dense (the near-binary Retinex
    weights), a power iteration converges slowly, and a Chebyshev smoother tuned below the
    true eigenvalue amplifies the modes above its interval.
    """
    g = torch.Generator(device="cpu").manual_seed(seed)
    s = dinv.clamp_min(0).sqrt()
    b = dinv.shape[0]
    # the same start for every item: a batch gives its items' one-by-one preconditioners
    x = torch.rand((1, *dinv.shape[1:]), generator=g, dtype=torch.float64) - 0.5
    q = x.to(dinv).expand_as(dinv).contiguous()
    q = q / q.flatten(1).norm(dim=1).clamp_min(torch.finfo(q.dtype).tiny).view(-1, 1, 1, 1)
    q_prev = torch.zeros_like(q)
    beta = torch.zeros(b, 1, 1, 1, dtype=q.dtype, device=q.device)
    alphas, betas = [], []
    for _ in range(max(1, iters)):
        w = s * matvec(s * q)
        alpha = (w * q).flatten(1).sum(1).view(-1, 1, 1, 1)
        w = w - alpha * q - beta * q_prev
        beta = w.flatten(1).norm(dim=1).view(-1, 1, 1, 1)
        alphas.append(alpha.flatten())
        betas.append(beta.flatten())
        # an exhausted Krylov space (beta ~ 0) is exact: that item's later steps add zeros
        live = beta > 1e-6 * alpha.abs().clamp_min(torch.finfo(q.dtype).tiny)
        q_prev, q = q, torch.where(live, w / beta.clamp_min(torch.finfo(q.dtype).tiny), 0)
        beta = torch.where(live, beta, 0)
    a = torch.stack(alphas, dim=1).to(torch.float64).cpu()  # (B, k)
    off = torch.stack(betas[:-1], dim=1).to(torch.float64).cpu() if len(betas) > 1 else None
    t = torch.diag_embed(a)
    if off is not None:
        t = t + torch.diag_embed(off, offset=1) + torch.diag_embed(off, offset=-1)
    lam: torch.Tensor = torch.linalg.eigvalsh(t)[:, -1]
    return lam.to(dtype=dinv.dtype, device=dinv.device).view(-1, 1, 1, 1)


def chebyshev(
    matvec: Operator,
    dinv: torch.Tensor,
    interval: tuple[torch.Tensor, float],
    degree: int,
    b: torch.Tensor,
    x: torch.Tensor | None,
) -> torch.Tensor:
    """``degree`` Chebyshev steps on ``A x = b`` in ``D^{-1} A`` (from ``x``, or from 0).

    ``interval``: ``(lambda_max, ratio)``, the polynomial is small on ``[lambda_max / ratio,
    lambda_max]`` (``lambda_max`` ``(B, 1, 1, 1)``, per item). The same polynomial before and
    after a coarse correction keeps the V-cycle symmetric.
    """
    lmax, ratio = interval
    lmin = lmax / ratio
    theta = (lmax + lmin) / 2
    delta = (lmax - lmin) / 2
    sigma = theta / delta
    rho = 1 / sigma
    r = dinv * (b if x is None else b - matvec(x))
    dvec = r / theta
    x = dvec.clone() if x is None else x + dvec
    for _ in range(degree - 1):
        r = r - dinv * matvec(dvec)
        rho_new = 1 / (2 * sigma - rho)
        dvec = (rho_new * rho) * dvec + (2 * rho_new / delta) * r
        rho = rho_new
        x = x + dvec
    return x
