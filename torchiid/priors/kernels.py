"""Compiled CPU kernels for the stencil products (numba), with the torch ops as the reference.

The solvers spend most of their time in weighted Laplacian products ``Mᵀ diag(w) M x`` over
both directions of every pair of a stencil: the shading PCG (a 5×5 stencil, 12 offsets) and
the Split-Bregman ``z`` step (an 11×11 stencil, 60 offsets, 3 channels). In torch each
direction of each offset is one strided ``addcmul`` over the whole image, ``2K`` passes over
memory per product. The kernel does one pass: every output row gathers its ``2K`` terms while
the rows it reads are in cache (``python tools/bench_kernels.py`` prints the comparison).

The kernel sums the pairs in difference form, ``Σ w (x_i − x_j)``, where the torch ops use
``deg ⊙ x − Σ w x_j``: the same operator, but it annihilates constants exactly and keeps its
round-off relative to the differences rather than to the values. That matters for float32
shading solves at the edge of what float32 resolves (the ``converged`` preset's), which the
``deg`` form can make break down.

The same one-pass kernels build the reflectance stage's 60-offset colour weights and the
matting Laplacian's stencil (once per alternation each), and update the reflectance stage's
Bregman variables (:mod:`torchiid.priors.bregman_pass`, whose names are importable from
here). Where the kernels apply and on which threads they run:
:mod:`torchiid.priors.kernel_runtime`.
"""

from __future__ import annotations

import math

import torch

from torchiid.priors import kernel_runtime
from torchiid.priors.bregman_pass import (
    bregman_replay,
    bregman_update,
    fixed_point_fits,
    fixed_point_scales,
)
from torchiid.priors.kernel_runtime import (
    bands,
    compiled,
    kernel_module,
    offset_arrays,
    parallel_lock,
    run_bands,
    usable,
)

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

#: the compiled kernels or ``None`` (:func:`~torchiid.priors.kernel_runtime.compiled`)
_numba = compiled


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


def _gather(
    x: torch.Tensor,
    weights: torch.Tensor,
    offsets: list[tuple[int, int]],
    square: bool,
    degree: bool,
) -> torch.Tensor:
    found = compiled()
    if found is None:
        raise RuntimeError("the compiled kernels are not available (see kernels.usable)")
    numba, kernel = found
    dys, dxs = offset_arrays(tuple(offsets))
    out = torch.empty_like(x)
    b, _, h, _ = x.shape
    args = (x.numpy(), weights.contiguous().numpy(), dys, dxs, out.numpy(), square, degree)
    n = min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
    if n <= 1:
        kernel.gather(*args, 0, b * h)
    else:  # numba's pool: a cheaper hand-off than bands for a sub-millisecond call
        with parallel_lock:
            small = x.numel() * 2 * len(offsets) < kernel_runtime.PARALLEL_WORK
            numba.set_num_threads(1 if small else n)
            kernel.gather_parallel(*args)
    return out


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
    kernel = kernel_module()
    b, _, h, w = image.shape
    qp = torch.empty(b, 11, h + 2, w + 2, dtype=torch.float64)
    qp[:, :, :2].zero_()  # the kernel writes every other entry (the window rows' borders too)
    qp[:, :, h:].zero_()
    m = torch.empty(0, 0, 0, 0, dtype=torch.bool)
    if mask is not None:
        m = mask.to(torch.bool).contiguous()
    args = (image.contiguous().numpy(), m.numpy(), float(eps), qp.numpy())
    rows = b * (h - 2)
    run_bands(kernel.matting_windows, args, bands(rows, b * h * w * 120))
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
    kernel = kernel_module()
    dys, dxs = offset_arrays(tuple(offsets))
    b, _, h, w = image.shape
    out = torch.empty(b, len(offsets), h, w, dtype=dtype)
    args = (window_terms.contiguous().numpy(), image.contiguous().numpy(), dys, dxs, out.numpy())
    run_bands(kernel.matting_weights, args, bands(b * h, b * h * w * len(offsets) * 40))
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
    about 3× faster than one ``exp`` call per pair in the kernel. Into ``out`` when given
    (``(B, K, H, W)``, the features' dtype; a non-contiguous one receives a copy). ``out``
    may be ``semantic`` itself (the same contiguous tensor, not broadcast): the weights then
    replace the factor, a few offsets at a time, with the values a new tensor would get.

    Shape:
        features ``(B, D, H, W)``, semantic ``(B, K, H, W)``, mask ``(B, 1, H, W)`` bool ->
        ``(B, K, H, W)``.
    """
    if semantic is not None and out is not None and out.data_ptr() == semantic.data_ptr():
        if out.shape != semantic.shape or out.stride() != semantic.stride():
            raise ValueError("out and semantic share their memory but are different views of it")
        return _affinity_over_factor(features, offsets, scale, out, a_l, a_m, mask, min_exponent)
    kernel = kernel_module()
    dys, dxs = offset_arrays(tuple(offsets))
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
    run_bands(kernel.affinity_exponent, args, bands(b * h, b * h * w * len(offsets) * (d + 4)))
    out.exp_()  # torch's exp is vectorised (the kernel's would be libm's, one call per pair)
    if sem is not None:
        rows = b * len(offsets) * h
        scaled = (out.view(rows, w).numpy(), sem.view(rows, w).numpy(), np_dt(a_l), np_dt(a_m))
        run_bands(kernel.scale_by_factor, scaled, bands(rows, rows * w * 2))
    if given is not None and given is not out:
        return given.copy_(out)
    return out


#: offsets per group of :func:`_affinity_over_factor`, whose scratch tensor holds one group
FACTOR_GROUP_OFFSETS = 8


def _affinity_over_factor(
    features: torch.Tensor,
    offsets: list[tuple[int, int]],
    scale: float,
    semantic: torch.Tensor,
    a_l: float,
    a_m: float,
    mask: torch.Tensor | None,
    min_exponent: float,
) -> torch.Tensor:
    """:func:`stencil_affinity` written over its factor ``semantic``, a few offsets at a time.

    Each group's exponents go to a scratch tensor of :data:`FACTOR_GROUP_OFFSETS` offsets,
    are exponentiated and scaled by the group's factors, and then replace them: the values
    are those of the one-pass path (every step is per element), without a second
    ``(B, K, H, W)`` tensor. ``semantic`` must be contiguous and of the output's shape.
    """
    kernel = kernel_module()
    b, d, h, w = features.shape
    nk = len(offsets)
    dt = features.dtype
    if semantic.shape != (b, nk, h, w) or semantic.dtype != dt or not semantic.is_contiguous():
        layout = "contiguous" if semantic.is_contiguous() else "non-contiguous"
        raise ValueError(
            f"weights written over their factor need a contiguous {dt} factor of shape "
            f"{(b, nk, h, w)}, got a {layout} {semantic.dtype} one of shape "
            f"{tuple(semantic.shape)}"
        )
    group = min(FACTOR_GROUP_OFFSETS, nk)
    scratch = torch.empty(1, group, h, w, dtype=dt)
    np_dt = scratch.numpy().dtype.type
    feats = features.contiguous()
    m = None if mask is None else mask.to(torch.bool).expand(b, 1, h, w).contiguous()
    none = torch.empty(0, 0, 0, 0, dtype=torch.bool).numpy()
    for i in range(b):
        f = feats[i : i + 1].numpy()
        mi = none if m is None else m[i : i + 1].numpy()
        for k0 in range(0, nk, group):
            n = min(group, nk - k0)
            part = scratch[:, :n]
            dys, dxs = offset_arrays(tuple(offsets[k0 : k0 + n]))
            args = (f, mi, dys, dxs, np_dt(scale), np_dt(min_exponent), part.numpy())
            run_bands(kernel.affinity_exponent, args, bands(h, h * w * n * (d + 4)))
            part.exp_()
            factor = semantic[i, k0 : k0 + n]
            rows = n * h
            scaled = (part.view(rows, w).numpy(), factor.view(rows, w).numpy(), np_dt(a_l))
            run_bands(kernel.scale_by_factor, (*scaled, np_dt(a_m)), bands(rows, rows * w * 2))
            factor.copy_(part[0])
    return semantic
