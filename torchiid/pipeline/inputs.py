"""The inputs of :func:`~torchiid.model.decompose`, checked and at the working resolution.

The method runs at a working resolution (``params.output.max_side`` on the longer side): the
image and the mask are brought there first, with the optional warm start ``init`` and a
video's temporal prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchiid.core.check import as_mask, check_image
from torchiid.core.exceptions import ParameterError, ShapeError
from torchiid.params import Parameters
from torchiid.pipeline.memory import check_memory
from torchiid.resample import downsample, working_size
from torchiid.stages.config import TemporalPrior

__all__ = [
    "WorkingInputs",
    "working_inputs",
    "check_inputs",
    "warm_start",
    "temporal_prior",
    "downsampled",
]


@dataclass(frozen=True)
class WorkingInputs:
    """:func:`~torchiid.model.decompose`'s inputs, checked, and at the working resolution.

    Attributes:
        full: ``(B, 3, H, W)`` the image at its resolution (float32 for half-precision input).
        full_mask: ``(B, 1, H, W)`` bool mask, or ``None``.
        dtype: the input's dtype (the layers are returned in it).
        image: ``(B, 3, h, w)`` the image at the working resolution, 0 outside the mask.
        mask: ``(B, 1, h, w)`` bool mask at the working resolution, or ``None``.
        first: the first alternation to run (``schedule_start``).
        log_shading0: ``(B, 1, h, w)`` the warm start's ``log S0``, or ``None``.
        reflectance0: ``(B, 3, h, w)`` the warm start's ``R0``, or ``None``.
        temporal: the temporal prior at the working resolution, or ``None``.
    """

    full: torch.Tensor
    full_mask: torch.Tensor | None
    dtype: torch.dtype
    image: torch.Tensor
    mask: torch.Tensor | None
    first: int
    log_shading0: torch.Tensor | None = None
    reflectance0: torch.Tensor | None = None
    temporal: TemporalPrior | None = None

    @property
    def size(self) -> tuple[int, int]:
        """``(h, w)``, the working resolution."""
        return (self.image.shape[-2], self.image.shape[-1])


def working_inputs(
    image: torch.Tensor,
    mask: torch.Tensor | None,
    params: Parameters,
    *,
    init: tuple[torch.Tensor, torch.Tensor] | None = None,
    temporal: TemporalPrior | None = None,
    schedule_start: int = 1,
    return_stage1: bool = True,
    return_iterations: bool = False,
) -> WorkingInputs:
    """Check :func:`~torchiid.model.decompose`'s inputs and bring them to the working size.

    A CPU decomposition that cannot fit in the memory left is refused here, before any work
    (:func:`~torchiid.pipeline.memory.check_memory`; the flags enter the estimate).
    """
    image, mask = check_inputs(image, mask, params)
    first = _first_alternation(schedule_start, params)
    in_dtype = image.dtype
    if in_dtype in (torch.float16, torch.bfloat16):
        image = image.float()
    big_h, big_w = image.shape[-2:]
    if image.device.type == "cpu":
        flags = {"return_stage1": return_stage1, "return_iterations": return_iterations}
        check_memory(big_h, big_w, params, image.shape[0], **flags)
    size = working_size(big_h, big_w, params.output.max_side)
    img, msk = downsampled(image, mask, size)
    patch = params.features.patch_size
    if min(size) < patch:
        needed = -(-patch * max(big_h, big_w) // min(big_h, big_w))  # the longer side for it
        fix = (
            f"--max-side {needed} or more, or 0 for the full resolution (max_side in Python)"
            if needed <= max(big_h, big_w)
            else "the photo is too narrow for them at any working resolution"
        )
        raise ParameterError(
            f"working resolution {size[1]}x{size[0]} (--max-side {params.output.max_side}) is "
            f"smaller than the {patch} px patches; {fix}"
        )
    s_init = z_init = None
    if init is not None:
        s_init, z_init = warm_start(init, image, size, msk, params)
    low = None if temporal is None else temporal_prior(temporal, image, size, msk)
    return WorkingInputs(image, mask, in_dtype, img, msk, first, s_init, z_init, low)


def _first_alternation(schedule_start: int, params: Parameters) -> int:
    if schedule_start == 1:
        return 1
    if not isinstance(schedule_start, int) or not 1 <= schedule_start <= params.iterations:
        raise ParameterError(
            f"schedule_start must be an alternation 1..{params.iterations}, got {schedule_start!r}"
        )
    return schedule_start


def downsampled(
    image: torch.Tensor, mask: torch.Tensor | None, size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The image and the mask at ``size``, the outside blacked out (it must not enter a prior)."""
    img = downsample(image, size)
    if mask is None:
        return img, None
    frac = downsample(mask.to(image.dtype), size)
    msk = frac > 0.5
    tiny = ~msk.flatten(1).any(1)  # a small mask can vanish at the working resolution
    msk[tiny] = frac[tiny] > 0
    return img * msk, msk


def check_inputs(
    image: torch.Tensor, mask: torch.Tensor | None, params: Parameters
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(image, mask)`` as ``(B, 3, H, W)`` and ``(B, 1, H, W)`` bool, or a one-line error."""
    if not isinstance(image, torch.Tensor):
        raise ShapeError(
            f"expected image to be a torch.Tensor, got {type(image).__name__}; pass linear RGB "
            "as a float tensor of shape (B, 3, H, W) or (3, H, W), e.g. "
            "torch.from_numpy(rgb).permute(2, 0, 1).float() for an (H, W, 3) array, or read "
            "a file with torchiid.io.load_image(path).image"
        )
    for name, x in (("image", image), ("mask", mask)):
        if isinstance(x, torch.Tensor) and x.device.type == "meta":
            raise ShapeError(
                f"{name} is on the meta device (a tensor without values); pass a tensor that "
                "holds values, on the CPU or a GPU"
            )
    if image.dim() == 3:
        image = image[None]
    check_image(image, "image", min_side=params.features.patch_size)
    if mask is not None:
        mask = as_mask(mask, image, "mask")
        empty = ~mask.flatten(1).any(1)
        if bool(empty.any()):
            raise ShapeError(f"mask of image {int(empty.nonzero()[0])} is empty (no pixel inside)")
    return image, mask


def warm_start(
    init: tuple[torch.Tensor, torch.Tensor],
    image: torch.Tensor,
    size: tuple[int, int],
    mask: torch.Tensor | None,
    params: Parameters,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(log S0, R0)`` of ``decompose(..., init=(R0, S0))`` at the working resolution."""
    if not isinstance(init, tuple | list) or len(init) != 2:
        raise ShapeError("init must be a pair (reflectance, shading) of tensors")
    r0, s0 = (torch.as_tensor(x).to(device=image.device, dtype=image.dtype) for x in init)
    r0 = r0[None] if r0.dim() == 3 else r0
    s0 = s0[None] if s0.dim() == 3 else s0
    b, _, big_h, big_w = image.shape
    if r0.dim() == 4 and tuple(r0.shape[-2:]) == tuple(size) and tuple(size) != (big_h, big_w):
        big_h, big_w = size  # given at the working resolution
    if tuple(r0.shape) != (b, 3, big_h, big_w):
        raise ShapeError(f"init reflectance must be {(b, 3, big_h, big_w)}, got {tuple(r0.shape)}")
    if (
        s0.dim() != 4
        or s0.shape[0] != b
        or s0.shape[1] not in (1, 3)
        or tuple(s0.shape[-2:]) != (big_h, big_w)
    ):
        raise ShapeError(f"init shading must be ({b}, 1, {big_h}, {big_w}), got {tuple(s0.shape)}")
    if not (torch.isfinite(r0).all() and torch.isfinite(s0).all()):
        raise ShapeError("init contains NaN or infinite values")
    floor = params.reflectance.shading_floor
    s0 = downsample(s0.mean(1, keepdim=True), size).clamp_min(floor).log()
    r0 = downsample(r0, size).clamp_min(0)
    if mask is not None:
        s0 = s0 * mask
    return s0.contiguous(), r0.contiguous()


def temporal_prior(
    prior: TemporalPrior,
    image: torch.Tensor,
    size: tuple[int, int],
    mask: torch.Tensor | None,
) -> TemporalPrior:
    """The temporal prior of ``decompose(..., temporal=)`` at the working resolution."""
    if not isinstance(prior, TemporalPrior):
        raise ShapeError(
            f"temporal must be a torchiid.stages.TemporalPrior, got {type(prior).__name__}"
        )
    b, _, big_h, big_w = image.shape
    target = torch.as_tensor(prior.target).to(device=image.device, dtype=image.dtype)
    conf = torch.as_tensor(prior.confidence).to(device=image.device, dtype=image.dtype)
    target = target[None] if target.dim() == 3 else target
    conf = conf[None] if conf.dim() == 3 else conf
    if tuple(target.shape[-2:]) == tuple(size) and tuple(size) != (big_h, big_w):
        big_h, big_w = size  # given at the working resolution
    if tuple(target.shape) != (b, 3, big_h, big_w):
        raise ShapeError(
            f"temporal target must be {(b, 3, big_h, big_w)}, got {tuple(target.shape)}"
        )
    if tuple(conf.shape) != (b, 1, big_h, big_w):
        raise ShapeError(
            f"temporal confidence must be {(b, 1, big_h, big_w)}, got {tuple(conf.shape)}"
        )
    if not (torch.isfinite(target).all() and torch.isfinite(conf).all()):
        raise ShapeError("temporal target or confidence contains NaN or infinite values")
    conf = conf.clamp(0, 1)
    # confidence-weighted averages: untrusted target pixels do not leak into trusted ones
    weighted = downsample(target.clamp_min(0) * conf, size)
    conf = downsample(conf, size)
    target = weighted / conf.clamp_min(1e-6)
    if mask is not None:
        conf = conf * mask
    return prior.replace(target=target.contiguous(), confidence=conf.contiguous())
