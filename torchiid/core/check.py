"""One home for input validation (tensor shapes, dtypes, finiteness).

Messages say what was expected and what came, e.g.
``expected image of shape (B, 3, H, W), got (2, 4, 8, 8)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchiid.core.exceptions import ImageError, ShapeError

__all__ = ["as_mask", "check_image", "check_same_batch", "check_finite", "check_shape"]

MIN_SIDE = 60


def check_shape(x: torch.Tensor, shape: Sequence[str | int], name: str = "tensor") -> None:
    """Check ``x`` against a symbolic shape such as ``("B", 3, "H", "W")``.

    Integers must match exactly; strings match any size (the same string must match the
    same size everywhere in the shape).
    """
    if not isinstance(x, torch.Tensor):
        raise ShapeError(f"expected {name} to be a torch.Tensor, got {type(x).__name__}")
    want = "(" + ", ".join(str(s) for s in shape) + ")"
    if x.dim() != len(shape):
        raise ShapeError(f"expected {name} of shape {want}, got {tuple(x.shape)}")
    seen: dict[str, int] = {}
    for dim, sym in zip(x.shape, shape, strict=True):
        if isinstance(sym, int):
            if dim != sym:
                raise ShapeError(f"expected {name} of shape {want}, got {tuple(x.shape)}")
        else:
            if sym in seen and seen[sym] != dim:
                raise ShapeError(f"expected {name} of shape {want}, got {tuple(x.shape)}")
            seen[sym] = dim


def check_finite(x: torch.Tensor, name: str = "tensor") -> None:
    """Raise :class:`ImageError` if ``x`` contains NaN or infinity.

    A finite sum proves every value finite (NaN and infinities propagate into it) in one cheap
    reduction, without the boolean tensor of ``isfinite(x).all()``; only a sum that is not
    finite (a bad value, or finite values that overflow it) takes the full check.
    """
    if x.numel() == 0 or bool(torch.isfinite(x.sum())):
        return
    if not bool(torch.isfinite(x).all()):
        n_nan = int(torch.isnan(x).sum())
        n_inf = int(torch.isinf(x).sum())
        raise ImageError(f"{name} contains {n_nan} NaN and {n_inf} infinite values")


def check_image(
    x: torch.Tensor,
    name: str = "image",
    channels: int | None = 3,
    min_side: int = 1,
    nonnegative: bool = True,
) -> None:
    """Validate a channel-first image batch ``(B, C, H, W)`` of floating dtype.

    Args:
        x: the tensor to check.
        name: how the tensor is called in error messages.
        channels: the required channel count, or ``None`` for any.
        min_side: the smallest allowed height and width.
        nonnegative: require all values ``>= 0`` (linear intensities).

    Raises:
        ShapeError: wrong type, rank, channel count or dtype.
        ImageError: too small, NaN/inf or negative values.
    """
    check_shape(x, ("B", channels if channels is not None else "C", "H", "W"), name)
    if not x.is_floating_point():
        raise ShapeError(f"expected {name} of floating dtype, got {x.dtype}; convert with .float()")
    if x.shape[0] == 0:
        raise ImageError(f"{name} is an empty batch (B = 0)")
    h, w = x.shape[-2:]
    if h < min_side or w < min_side:
        raise ImageError(f"{name} is {w}x{h} px; at least {min_side} px per side is needed")
    check_finite(x, name)
    if nonnegative and bool((x < 0).any()):
        raise ImageError(f"{name} has negative values; expected linear intensities >= 0")


def check_same_batch(*tensors: torch.Tensor, names: Sequence[str] | None = None) -> None:
    """Check that tensors share batch size and spatial size ``(H, W)``."""
    names = list(names) if names is not None else [f"tensor {i}" for i in range(len(tensors))]
    ref = tensors[0]
    for t, n in zip(tensors[1:], names[1:], strict=False):
        if t.shape[0] != ref.shape[0] or t.shape[-2:] != ref.shape[-2:]:
            raise ShapeError(
                f"{n} has shape {tuple(t.shape)} but {names[0]} has shape {tuple(ref.shape)}; "
                "batch size and (H, W) must match"
            )


def as_mask(mask: torch.Tensor | None, like: torch.Tensor, name: str = "mask") -> torch.Tensor:
    """A bool ``(B, 1, H, W)`` mask for ``like`` ``(B, C, H, W)``: nonzero is inside.

    Accepts ``(H, W)``, ``(B, H, W)`` or ``(B or 1, 1, H, W)``; ``None`` means all inside.
    """
    b, _, h, w = like.shape
    if mask is None:
        return torch.ones(b, 1, h, w, dtype=torch.bool, device=like.device)
    if not isinstance(mask, torch.Tensor):
        raise ShapeError(
            f"expected {name} to be a torch.Tensor (bool or numbers, nonzero = inside), "
            f"got {type(mask).__name__}; use torch.as_tensor"
        )
    if mask.dim() == 2:
        mask = mask[None, None]
    elif mask.dim() == 3:
        mask = mask[:, None]
    check_shape(mask, ("B", 1, "H", "W"), name)
    if mask.shape[-2:] != (h, w) or mask.shape[0] not in (1, b):
        raise ShapeError(f"{name} has shape {tuple(mask.shape)}, expected ({b} or 1, 1, {h}, {w})")
    return (mask.to(like.device) != 0).expand(b, 1, h, w)
