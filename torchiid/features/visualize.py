"""Pictures of the Stage-0 features (paper Fig. 3): PCA image, proposal masks, patch grid.

Every function returns an ``HxWx3`` ``uint8`` **sRGB** array ready to be saved (e.g. with
``cv2.imwrite(path, out[..., ::-1])`` or ``skimage.io.imsave``). Photos are passed in as sRGB:
an ``HxWx3`` ``uint8`` array, an ``HxWx3`` float array in ``[0, 1]``, or a float tensor
``(3, H, W)`` / ``(1, 3, H, W)`` in ``[0, 1]`` (convert linear images first, e.g. with
:func:`torchiid.core.colour.linear_to_srgb`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.features.midlevel import MidLevelFeatures
from torchiid.features.proposals import Proposals

__all__ = ["draw_patch_grid", "overlay_masks", "pca_image", "select_masks", "to_uint8_image"]

_PALETTE = np.array(
    [
        [230, 25, 75],
        [60, 180, 75],
        [255, 225, 25],
        [0, 130, 200],
        [245, 130, 48],
        [145, 30, 180],
        [70, 240, 240],
        [240, 50, 230],
        [210, 245, 60],
        [250, 190, 212],
    ],
    dtype=np.uint8,
)


def to_uint8_image(image: np.ndarray | torch.Tensor, name: str = "image") -> np.ndarray:
    """An sRGB image as a contiguous ``HxWx3`` ``uint8`` array (floats clipped to ``[0, 1]``).

    Shape:
        - Input: ``(H, W, 3)`` array, or ``(3, H, W)`` / ``(1, 3, H, W)`` tensor.
        - Output: ``(H, W, 3)`` uint8.
    """
    if isinstance(image, torch.Tensor):
        t = image.detach()
        if t.dim() == 4 and t.shape[0] == 1:
            t = t[0]
        if t.dim() != 3 or t.shape[0] != 3:
            raise ShapeError(
                f"expected {name} tensor of shape (3, H, W) or (1, 3, H, W), "
                f"got {tuple(image.shape)}"
            )
        arr = t.permute(1, 2, 0).cpu().numpy()
    elif isinstance(image, np.ndarray):
        arr = image
    else:
        raise ShapeError(f"expected {name} as a numpy array or tensor, got {type(image).__name__}")
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ShapeError(f"expected {name} of shape (H, W, 3), got {arr.shape}")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if not np.issubdtype(arr.dtype, np.floating):
        raise ShapeError(f"expected {name} as uint8 or float in [0, 1], got dtype {arr.dtype}")
    if not np.isfinite(arr).all():
        raise ImageError(f"{name} contains NaN or infinite values")
    return np.ascontiguousarray(np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8))


def pca_image(mid: MidLevelFeatures | torch.Tensor, method: str = "auto") -> np.ndarray:
    """The paper's "PCA image" (Fig. 3): the first 3 PCA components of ``g_i`` as RGB.

    Each component is min-max scaled to ``[0, 255]`` independently (a constant component is 0).

    Args:
        mid: mid-level features, or an already reduced ``(1, d, H, W)`` / ``(d, H, W)`` tensor
            with ``d >= 3`` (its first three channels are used).
        method: PCA method passed to :meth:`MidLevelFeatures.pca`.

    Shape:
        - Output: ``(H, W, 3)`` uint8.
    """
    if isinstance(mid, MidLevelFeatures):
        dim = min(3, mid.num_proposals)
        x = mid.pca(dim, method)[0]
    elif isinstance(mid, torch.Tensor):
        x = mid[0] if mid.dim() == 4 and mid.shape[0] == 1 else mid
        if x.dim() != 3:
            raise ShapeError(
                f"expected PCA features of shape (1, d, H, W) or (d, H, W), got {tuple(mid.shape)}"
            )
    else:
        raise ShapeError(f"expected MidLevelFeatures or a tensor, got {type(mid).__name__}")
    x = x[:3].detach().to("cpu", torch.float64)
    if x.shape[0] < 3:
        x = torch.cat([x, x.new_zeros(3 - x.shape[0], *x.shape[1:])])
    lo = x.amin(dim=(1, 2), keepdim=True)
    span = x.amax(dim=(1, 2), keepdim=True) - lo
    y = torch.where(span > 0, (x - lo) / span.clamp_min(1e-300), torch.zeros_like(x))
    return np.ascontiguousarray((y * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy())


def select_masks(
    proposals: Proposals,
    n: int = 4,
    min_area: float = 0.02,
    max_area: float = 0.6,
    max_iou: float = 0.3,
) -> torch.Tensor:
    """Indices of ``n`` well-ranked, mutually distinct proposals worth showing.

    Walks the proposals in rank order and keeps those covering a fraction of the image in
    ``[min_area, max_area]`` whose intersection-over-union with every kept one is at most
    ``max_iou``; if fewer than ``n`` qualify, the best-ranked others fill up.

    Returns:
        ``(n',)`` long indices, ``n' = min(n, P)``, for :meth:`Proposals.masks`.
    """
    if n < 1:
        raise ParameterError(f"n must be >= 1, got {n}")
    h, w = proposals.shape
    frac = proposals.areas.double() / (h * w)
    member = proposals.membership.double()
    sizes = proposals.atom_sizes.double()
    ok = torch.nonzero((frac >= min_area) & (frac <= max_area)).flatten().tolist()
    chosen: list[int] = []
    for c in ok:  # loop over proposals, not pixels
        if len(chosen) == n:
            break
        if chosen:
            inter = (sizes * member[:, c]) @ member[:, chosen]
            union = proposals.areas[c] + proposals.areas[chosen] - inter
            if float((inter / union).max()) > max_iou:
                continue
        chosen.append(c)
    for c in range(proposals.num_proposals):
        if len(chosen) >= n:
            break
        if c not in chosen:
            chosen.append(c)
    return torch.tensor(chosen, dtype=torch.long)


def overlay_masks(
    image_srgb: np.ndarray | torch.Tensor,
    masks: np.ndarray | torch.Tensor,
    alpha: float = 0.5,
    columns: int | None = None,
    contour: bool = True,
) -> np.ndarray:
    """Proposal masks overlaid on the photo, one tile per mask, each in its own colour.

    Args:
        image_srgb: the photo, sRGB (see the module docstring).
        masks: ``(N, H, W)`` boolean (or 0/1) masks, e.g. ``proposals.masks([0, 1, 2, 3])``.
        alpha: opacity of the colour inside a mask.
        columns: tiles per row of the mosaic; ``None`` puts all ``N`` in one row.
        contour: draw the mask outline in full colour.

    Shape:
        - Output: ``(rows * H, columns * W, 3)`` uint8, tiles left to right, top to bottom
          (unused tiles black).
    """
    img = to_uint8_image(image_srgb, "image_srgb")
    m = masks.detach().cpu().numpy() if isinstance(masks, torch.Tensor) else np.asarray(masks)
    h, w, _ = img.shape
    if m.ndim == 2:
        m = m[None]
    if m.ndim != 3 or m.shape[1:] != (h, w) or m.shape[0] == 0:
        raise ShapeError(f"expected masks of shape (N, {h}, {w}) with N >= 1, got {m.shape}")
    if not 0.0 <= alpha <= 1.0:
        raise ParameterError(f"alpha must lie in [0, 1], got {alpha}")
    n = m.shape[0]
    cols = n if columns is None else int(columns)
    if cols < 1:
        raise ParameterError(f"columns must be >= 1, got {columns}")
    rows = math.ceil(n / cols)
    out = np.zeros((rows * h, cols * w, 3), dtype=np.uint8)
    base = img.astype(np.float32)
    import cv2  # on first use, once per call (see torchiid.features.proposal_features)

    for i in range(n):  # one tile per mask; pixels are vectorised
        mask = m[i].astype(bool)
        colour = _PALETTE[i % len(_PALETTE)].astype(np.float32)
        tile = np.where(mask[..., None], (1 - alpha) * base + alpha * colour, base)
        tile = tile.round().astype(np.uint8)
        if contour:
            cnts, _ = cv2.findContours(
                mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
            )
            cv2.drawContours(tile, cnts, -1, tuple(int(c) for c in _PALETTE[i % len(_PALETTE)]), 1)
        r, c = divmod(i, cols)
        out[r * h : (r + 1) * h, c * w : (c + 1) * w] = tile
    return out


def draw_patch_grid(
    image_srgb: np.ndarray | torch.Tensor,
    grid: np.ndarray | torch.Tensor | Sequence[Sequence[float]],
    colour: tuple[int, int, int] = (255, 255, 0),
    thickness: int = 1,
    radius: int = 2,
    centres: bool = True,
) -> np.ndarray:
    """Draw a patch grid (e.g. from ``torchiid.features.patches.patch_grid``) on the photo.

    Args:
        image_srgb: the photo, sRGB (see the module docstring).
        grid: ``(N, 4)`` boxes ``x0, y0, x1, y1`` (pixels; ``x1, y1`` exclusive), drawn as
            rectangles, or ``(N, 2)`` centres ``(y, x)``, drawn as dots.
        colour: RGB colour of the drawing.
        thickness: rectangle line width in pixels.
        radius: dot radius for centres.
        centres: with boxes, also mark each box centre with a dot.

    Shape:
        - Output: ``(H, W, 3)`` uint8.
    """
    img = to_uint8_image(image_srgb, "image_srgb").copy()
    g = grid.detach().cpu().numpy() if isinstance(grid, torch.Tensor) else np.asarray(grid)
    if g.ndim != 2 or g.shape[1] not in (2, 4):
        raise ShapeError(f"expected grid boxes (N, 4) or centres (N, 2), got shape {g.shape}")
    if not np.isfinite(g).all():
        raise ParameterError("grid contains NaN or infinite coordinates")
    col = tuple(int(c) for c in colour)
    pts = np.round(g).astype(np.int64)
    import cv2  # on first use, once per call (see torchiid.features.proposal_features)

    for row in pts.tolist():  # one call per patch, not per pixel
        if len(row) == 4:
            x0, y0, x1, y1 = row
            cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), col, int(thickness))
            if centres:
                cv2.circle(img, ((x0 + x1 - 1) // 2, (y0 + y1 - 1) // 2), int(radius), col, -1)
        else:
            y, x = row
            cv2.circle(img, (x, y), int(radius), col, -1)
    return img
