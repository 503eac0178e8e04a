"""Fixed-offset neighbourhoods ("stencils") as weighted difference operators.

A stencil of odd ``size`` pairs every pixel ``i`` with the pixels ``j = i + (dy, dx)`` of its
``size x size`` window. Each unordered pair is listed once: :func:`half_offsets` keeps the
offsets in the "positive" half-plane. For ``K`` offsets the weights of all pairs live in a
``(B, K, H, W)`` tensor indexed by the first pixel ``i``; pairs whose second pixel falls outside
the image have weight 0 (they are masked by :meth:`Stencil.valid`).

The difference operator ``M`` maps an image ``x`` of shape ``(B, C, H, W)`` to the pair
differences ``(M x)[b, c, k, y, x] = x[b, c, y, x] - x[b, c, y + dy_k, x + dx_k]`` and
``M^T`` scatters them back. The weighted quadratic form ``x^T M^T W M x`` is a graph Laplacian;
:meth:`Stencil.laplacian_matvec` applies it with shifts, and :meth:`Stencil.difference_matrix`
builds the same operator as a torch sparse (COO) block-diagonal matrix, the canonical reference.
"""

from __future__ import annotations

from functools import cached_property

import torch

__all__ = ["half_offsets", "shift_slices", "Stencil"]


def half_offsets(size: int) -> list[tuple[int, int]]:
    """Offsets ``(dy, dx)`` listing each unordered pair of a ``size x size`` window once.

    Keeps ``(dy, dx)`` with ``dy > 0``, or ``dy == 0 and dx > 0``. A 3x3 window gives 4
    offsets, an 11x11 window 60.

    >>> half_offsets(3)
    [(0, 1), (1, -1), (1, 0), (1, 1)]
    """
    if size < 3 or size % 2 == 0:
        raise ValueError(f"stencil size must be odd and >= 3, got {size}")
    r = size // 2
    out = []
    for dy in range(0, r + 1):
        for dx in range(-r, r + 1):
            if dy > 0 or dx > 0:
                out.append((dy, dx))
    return out


def shift_slices(dy: int, dx: int, h: int, w: int) -> tuple[slice, slice, slice, slice]:
    """Slices ``(ys_i, xs_i, ys_j, xs_j)`` such that ``j = i + (dy, dx)`` stays inside.

    ``x[..., ys_i, xs_i]`` are the pixels ``i`` of an ``h x w`` grid whose partner
    ``j = i + (dy, dx)`` lies inside the grid, and ``x[..., ys_j, xs_j]`` those partners.

    >>> shift_slices(1, -1, 4, 5)
    (slice(0, 3, None), slice(1, 5, None), slice(1, 4, None), slice(0, 4, None))
    """
    ys_i = slice(max(0, -dy), h - max(0, dy))
    xs_i = slice(max(0, -dx), w - max(0, dx))
    ys_j = slice(max(0, dy), h - max(0, -dy))
    xs_j = slice(max(0, dx), w - max(0, -dx))
    return ys_i, xs_i, ys_j, xs_j


class Stencil:
    """Pairs of a fixed-offset neighbourhood on an ``H x W`` grid.

    Args:
        height: image height ``H``.
        width: image width ``W``.
        offsets: the ``K`` offsets ``(dy, dx)``; use :func:`half_offsets`.
        device: where index and mask tensors live.
    """

    def __init__(
        self,
        height: int,
        width: int,
        offsets: list[tuple[int, int]],
        device: torch.device | str | None = None,
    ) -> None:
        if not offsets:
            raise ValueError("a stencil needs at least one offset")
        self.height = int(height)
        self.width = int(width)
        self.offsets = [(int(dy), int(dx)) for dy, dx in offsets]
        self.device = torch.device(device) if device is not None else torch.device("cpu")

    @classmethod
    def square(
        cls, height: int, width: int, size: int, device: torch.device | str | None = None
    ) -> Stencil:
        """The stencil of all unordered pairs in a ``size x size`` window."""
        return cls(height, width, half_offsets(size), device)

    @property
    def num_offsets(self) -> int:
        """``K``, the number of offsets."""
        return len(self.offsets)

    @cached_property
    def valid(self) -> torch.Tensor:
        """``(K, H, W)`` bool mask: pair ``(i, i + offset_k)`` lies inside the image."""
        m = torch.zeros(
            self.num_offsets, self.height, self.width, dtype=torch.bool, device=self.device
        )
        for k, (dy, dx) in enumerate(self.offsets):
            ys_i, xs_i, _, _ = shift_slices(dy, dx, self.height, self.width)
            m[k, ys_i, xs_i] = True
        return m

    def neighbours(self, x: torch.Tensor) -> torch.Tensor:
        """Values at the second pixel of every pair: ``(B, C, H, W) -> (B, C, K, H, W)``.

        Entries of invalid pairs are 0.
        """
        b, c, h, w = x.shape
        out = x.new_zeros(b, c, self.num_offsets, h, w)
        for k, (dy, dx) in enumerate(self.offsets):
            ys_i, xs_i, ys_j, xs_j = shift_slices(dy, dx, h, w)
            out[:, :, k, ys_i, xs_i] = x[:, :, ys_j, xs_j]
        return out

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Pair differences ``M x``: ``(B, C, H, W) -> (B, C, K, H, W)``, 0 for invalid pairs."""
        diff = x.unsqueeze(2) - self.neighbours(x)
        return diff * self.valid.to(x.dtype)

    def adjoint(self, d: torch.Tensor, zero_invalid: bool = True) -> torch.Tensor:
        """``M^T d``: scatter pair values ``(B, C, K, H, W)`` back to ``(B, C, H, W)``.

        ``zero_invalid=False`` skips masking the pairs that leave the image, for values that
        are 0 there already.
        """
        b, c, k_, h, w = d.shape
        if zero_invalid:
            d = d * self.valid.to(d.dtype)
        out = d.sum(dim=2)
        for k, (dy, dx) in enumerate(self.offsets):
            ys_i, xs_i, ys_j, xs_j = shift_slices(dy, dx, h, w)
            out[:, :, ys_j, xs_j] -= d[:, :, k, ys_i, xs_i]
        return out

    def laplacian_matvec(self, weights: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``M^T diag(w) M x`` for pair weights ``(B, K, H, W)`` and ``x`` ``(B, C, H, W)``."""
        return self.adjoint(weights.unsqueeze(1) * self.apply(x))

    def laplacian_diagonal(self, weights: torch.Tensor, zero_invalid: bool = True) -> torch.Tensor:
        """Diagonal of ``M^T diag(w) M``: ``(B, K, H, W) -> (B, 1, H, W)`` (Jacobi).

        ``zero_invalid=False`` skips masking the pairs that leave the image, for weights that
        are 0 there already.
        """
        w = weights * self.valid.to(weights.dtype) if zero_invalid else weights
        out = w.sum(dim=1, keepdim=True)
        h, wd = self.height, self.width
        for k, (dy, dx) in enumerate(self.offsets):
            ys_i, xs_i, ys_j, xs_j = shift_slices(dy, dx, h, wd)
            out[:, 0, ys_j, xs_j] += w[:, k, ys_i, xs_i]
        return out

    def pair_index(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat indices of all valid pairs.

        Returns:
            ``(k, i, j)``: offset index, first and second pixel's flat index ``y * W + x``
            (within one image), each of shape ``(P,)`` in the order of ``weights[:, k, y, x]``.
        """
        k, y, x = torch.nonzero(self.valid, as_tuple=True)
        dy = torch.tensor([o[0] for o in self.offsets], device=self.device)[k]
        dx = torch.tensor([o[1] for o in self.offsets], device=self.device)[k]
        i = y * self.width + x
        j = (y + dy) * self.width + (x + dx)
        return k, i, j

    def difference_matrix(
        self, weights: torch.Tensor | None = None, batch: int = 1
    ) -> torch.Tensor:
        """The (optionally weighted) difference operator as a sparse COO matrix.

        Args:
            weights: ``(B, K, H, W)`` pair weights; rows are scaled by ``sqrt(w)`` so that
                ``D^T D`` equals ``M^T diag(w) M``. ``None`` means all ones.
            batch: number of images when ``weights`` is ``None``.

        Returns:
            Block-diagonal sparse matrix of shape ``(B * P, B * H * W)``, one row per valid
            pair and image, ``+sqrt(w)`` at ``i`` and ``-sqrt(w)`` at ``j``.
        """
        k, i, j = self.pair_index()
        n = self.height * self.width
        p = k.numel()
        if weights is not None:
            batch = weights.shape[0]
            ys, xs = torch.div(i, self.width, rounding_mode="floor"), i % self.width
            sw = weights[:, k, ys, xs].clamp_min(0).sqrt()  # (B, P)
            dtype = weights.dtype
        else:
            sw = torch.ones(batch, p, device=self.device)
            dtype = torch.float32
        offs_row = (torch.arange(batch, device=self.device) * p).view(-1, 1)
        offs_col = (torch.arange(batch, device=self.device) * n).view(-1, 1)
        rows = (torch.arange(p, device=self.device).view(1, -1) + offs_row).reshape(-1)
        ci = (i.view(1, -1) + offs_col).reshape(-1)
        cj = (j.view(1, -1) + offs_col).reshape(-1)
        idx = torch.stack([torch.cat([rows, rows]), torch.cat([ci, cj])])
        val = torch.cat([sw.reshape(-1), -sw.reshape(-1)]).to(dtype)
        return torch.sparse_coo_tensor(
            idx, val, (batch * p, batch * n), check_invariants=False
        ).coalesce()
