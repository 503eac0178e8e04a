"""CNN patch features ``f_b`` on a fixed grid (paper §3.1.1, Table 1: 60x60 patches, stride 30).

Each patch ``b`` gets a 1280-d EfficientNet-Lite0 descriptor (pooled penultimate features, standing
in for the paper's 4096-d ``fc7``), assigned to the patch centre. Two modes:

- ``"shared"`` (default, fast): one forward pass over the whole image, upscaled by ``scale``, then
  each patch's features are pooled from the stride-32 feature map with RoI-align (Fast R-CNN
  style) and averaged. With ``scale = 2`` a 60 px patch spans 120 px, about four feature cells.
- ``"crop"`` (the paper's protocol): each patch is cut out, resized to 224x224 and run through the
  network on its own (in batches); the 7x7 map is averaged.

Colour: the input is **linear** RGB in ``[0, 1]`` (the pipeline's working space); it is encoded to
sRGB with the sRGB curve (:func:`torchiid.core.colour.linear_to_srgb`, as
:func:`kornia.color.linear_rgb_to_rgb`) and clipped to ``[0, 1]`` before the network, which was
trained on sRGB photos.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import nn

from torchiid.core.check import check_image
from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ParameterError
from torchiid.features import onnx_backend
from torchiid.features.backbone import (
    FEATURE_DIM,
    FEATURE_STRIDE,
    FeatureMapExtractor,
    efficientnet_lite0,
    feature_offset,
)
from torchiid.features.onnx_backend import OnnxFeatureExtractor
from torchiid.features.roi import roi_align

__all__ = [
    "PatchFeatureExtractor",
    "PatchFeatures",
    "PatchGrid",
    "patch_features",
    "patch_grid",
    "release_feature_extractors",
]

CROP_SIZE = 224
_POOL_POINTS = 4  # RoI-align samples per side in shared mode (about one per feature cell)


@dataclass(frozen=True)
class PatchGrid:
    """A regular grid of square patches covering an image.

    Attributes:
        boxes: ``(N, 4)`` long, ``(x1, y1, x2, y2)`` pixel edges (``x2 = x1 + size``, exclusive).
        centers: ``(N, 2)`` long, ``(y, x)`` pixel index of each patch centre (``y1 + size // 2``).
        shape: ``(rows, cols)`` of the grid; patches are listed row-major, ``N = rows * cols``.
        height: image height ``H``.
        width: image width ``W``.
        size: patch side in pixels.
        stride: grid step in pixels (the last row/column may be closer, flush with the border).
    """

    boxes: torch.Tensor
    centers: torch.Tensor
    shape: tuple[int, int]
    height: int
    width: int
    size: int
    stride: int

    def __len__(self) -> int:
        return self.boxes.shape[0]


@dataclass(frozen=True)
class PatchFeatures:
    """Patch descriptors ``f_b`` and the grid they belong to.

    Attributes:
        grid: the :class:`PatchGrid`.
        features: ``(B, N, 1280)`` non-negative descriptors, dtype/device of the input image.
        mode: ``"shared"`` or ``"crop"``.
    """

    grid: PatchGrid
    features: torch.Tensor
    mode: str


def _starts(length: int, size: int, stride: int) -> torch.Tensor:
    starts = torch.arange(0, length - size + 1, stride)
    if starts[-1] != length - size:
        starts = torch.cat((starts, torch.tensor([length - size])))
    return starts


def patch_grid(
    height: int, width: int, size: int = 60, stride: int = 30, device: torch.device | None = None
) -> PatchGrid:
    """Grid of ``size x size`` patches every ``stride`` pixels, covering the whole image.

    When ``H - size`` (or ``W - size``) is not a multiple of ``stride`` a last row (column) flush
    with the bottom (right) border is added, so every pixel lies in at least one patch.

    Args:
        height: image height ``H`` (``>= size``).
        width: image width ``W`` (``>= size``).
        size: patch side in pixels (paper: 60).
        stride: step in pixels (paper: 30).
        device: device of the returned tensors.

    Returns:
        The :class:`PatchGrid`.

    Raises:
        ParameterError: ``size`` or ``stride`` < 1, or the image is smaller than a patch.

    >>> g = patch_grid(100, 130)
    >>> g.shape, g.boxes[-1].tolist(), g.centers[-1].tolist()
    ((3, 4), [70, 40, 130, 100], [70, 100])
    """
    if size < 1 or stride < 1:
        raise ParameterError(f"patch size and stride must be >= 1, got {size} and {stride}")
    if height < size or width < size:
        raise ParameterError(f"image of {height}x{width} pixels is smaller than a {size} px patch")
    ys = _starts(height, size, stride)
    xs = _starts(width, size, stride)
    y1, x1 = torch.meshgrid(ys, xs, indexing="ij")
    y1, x1 = y1.reshape(-1), x1.reshape(-1)
    boxes = torch.stack((x1, y1, x1 + size, y1 + size), dim=1).to(device)
    centers = torch.stack((y1 + size // 2, x1 + size // 2), dim=1).to(device)
    return PatchGrid(boxes, centers, (len(ys), len(xs)), height, width, size, stride)


@lru_cache(maxsize=4)
def _torch_extractor(device: str) -> FeatureMapExtractor:
    model = FeatureMapExtractor(efficientnet_lite0(pretrained=True)).to(device)
    return model.eval().requires_grad_(False)


def _shared(srgb: torch.Tensor, grid: PatchGrid, feature_map, scale: float) -> torch.Tensor:
    h, w = srgb.shape[-2:]
    hs, ws = max(round(h * scale), 1), max(round(w * scale), 1)
    x = srgb
    if (hs, ws) != (h, w):
        x = F.interpolate(srgb, size=(hs, ws), mode="bilinear", align_corners=False)
    fmap = _feature_map(x, feature_map)  # (B, 1280, ceil(hs/32), ceil(ws/32))
    # Pixel edge coordinate u of the input -> u * hs / h in the resized image -> feature-map
    # coordinate (cell j spans [j, j+1)): cell j is centred on resized pixel 32 j + offset.
    sy, sx = hs / h, ws / w
    oy, ox = feature_offset(hs) + 0.5, feature_offset(ws) + 0.5
    b = grid.boxes.to(device=fmap.device, dtype=fmap.dtype)
    scale_t = torch.tensor([sx, sy, sx, sy], device=fmap.device, dtype=fmap.dtype)
    shift_t = torch.tensor([ox, oy, ox, oy], device=fmap.device, dtype=fmap.dtype)
    boxes = (b * scale_t - shift_t) / FEATURE_STRIDE + 0.5
    pooled = roi_align(fmap, boxes, _POOL_POINTS, sampling_ratio=1)  # (B, N, C, 4, 4)
    return pooled.mean(dim=(-2, -1))


def _feature_map(x: torch.Tensor, feature_map) -> torch.Tensor:
    """The CNN's feature map of a batch; through onnxruntime, one image at a time.

    onnxruntime on the CPU gains nothing from a batch: the images' activations only make its
    arena larger (and it is handed back after the last image), so a batch costs more time and
    memory than its images one by one, with the same values.
    """
    if not isinstance(feature_map, OnnxFeatureExtractor) or x.shape[0] == 1:
        return feature_map(x)
    n = x.shape[0]
    return torch.cat([feature_map(x[i : i + 1], release_memory=i == n - 1) for i in range(n)])


def _crop(srgb: torch.Tensor, grid: PatchGrid, feature_map, batch_size: int) -> torch.Tensor:
    bsz = srgb.shape[0]
    size = grid.size
    offs = torch.arange(size, device=srgb.device)
    rows = grid.boxes[:, 1].to(srgb.device)[:, None] + offs  # (N, size)
    cols = grid.boxes[:, 0].to(srgb.device)[:, None] + offs
    patches = srgb[:, :, rows[:, :, None], cols[:, None, :]]  # (B, 3, N, size, size)
    patches = patches.permute(0, 2, 1, 3, 4).reshape(-1, 3, size, size)
    out = []
    chunks = patches.split(batch_size)
    for i, chunk in enumerate(chunks):
        x = F.interpolate(chunk, size=(CROP_SIZE, CROP_SIZE), mode="bilinear", align_corners=False)
        if isinstance(feature_map, OnnxFeatureExtractor):
            # onnxruntime keeps its arena between the chunks and gives it back after the last
            fmap = feature_map(x, release_memory=i == len(chunks) - 1)
        else:
            fmap = feature_map(x)
        out.append(fmap.mean(dim=(-2, -1)))
    return torch.cat(out).reshape(bsz, len(grid), FEATURE_DIM)


def _compute(image, grid, feature_map, mode, scale, batch_size, srgb_input) -> torch.Tensor:
    x = image.float()
    srgb = x.clamp(0.0, 1.0) if srgb_input else linear_to_srgb(x)
    if mode == "shared":
        return _shared(srgb, grid, feature_map, scale)
    return _crop(srgb, grid, feature_map, batch_size)


def _check_args(image, size, stride, mode, scale, batch_size) -> PatchGrid:
    check_image(image, "image", channels=3, min_side=max(size, 1))
    if mode not in ("shared", "crop"):
        raise ParameterError(f"mode must be 'shared' or 'crop', got {mode!r}")
    if not scale > 0:
        raise ParameterError(f"scale must be > 0, got {scale}")
    if batch_size < 1:
        raise ParameterError(f"batch_size must be >= 1, got {batch_size}")
    return patch_grid(image.shape[-2], image.shape[-1], size, stride, device=image.device)


def patch_features(
    image: torch.Tensor,
    mode: str = "shared",
    backend: str = "onnx",
    size: int = 60,
    stride: int = 30,
    scale: float = 2.0,
    batch_size: int = 32,
    srgb_input: bool = False,
    onnx_extractor: OnnxFeatureExtractor | None = None,
) -> PatchFeatures:
    """CNN descriptors ``f_b`` of the ``size x size`` patches of a stride-``stride`` grid.

    Args:
        image: **linear** RGB batch in ``[0, 1]`` (values above 1 are clipped after sRGB
            encoding); with ``srgb_input=True``, already sRGB-encoded.
        mode: ``"shared"`` (one pass + RoI-align, fast) or ``"crop"`` (one pass per patch,
            resized to 224, as in the paper).
        backend: ``"onnx"`` (onnxruntime; the model is exported to the cache on first use) or
            ``"torch"``. Both compute in float32 without gradients.
        size: patch side in pixels (paper: 60).
        stride: grid step in pixels (paper: 30).
        scale: shared mode only: the image is resized by this factor before the forward pass,
            so a patch spans ``size * scale / 32`` feature cells (2.0: about 4).
        batch_size: crop mode only: patches per forward pass.
        srgb_input: the image is already sRGB (skip the linear -> sRGB encoding).
        onnx_extractor: a prepared :class:`OnnxFeatureExtractor` (default: a cached one).

    Returns:
        :class:`PatchFeatures` with ``features`` ``(B, N, 1280)`` of the input's dtype/device.

    Shape:
        - image: ``(B, 3, H, W)``, ``H, W >= size``
        - features: ``(B, N, 1280)``, ``N = rows * cols`` of :func:`patch_grid`

    Raises:
        ShapeError: not a ``(B, 3, H, W)`` floating tensor.
        ImageError: NaN/inf or negative values, or a side shorter than ``size``.
        ParameterError: unknown mode/backend or invalid numbers.
    """
    grid = _check_args(image, size, stride, mode, scale, batch_size)
    if backend == "onnx":
        extractor = onnx_extractor or _default_onnx(image.device.type)
        feature_map = extractor
    elif backend == "torch":
        feature_map = _torch_extractor(str(image.device))
    else:
        raise ParameterError(f"backend must be 'onnx' or 'torch', got {backend!r}")
    with torch.no_grad():
        feats = _compute(image, grid, feature_map, mode, scale, batch_size, srgb_input)
    return PatchFeatures(grid, feats.to(image.dtype), mode)


@lru_cache(maxsize=2)
def _default_onnx(device_type: str) -> OnnxFeatureExtractor:
    return OnnxFeatureExtractor(device=device_type)


def release_feature_extractors() -> None:
    """Forget the CNNs that :func:`patch_features` keeps between calls.

    :func:`patch_features` keeps its onnxruntime session (about 50 MB with the weights) and
    its torch backbone for the next image. A process with no image left to describe can
    give that memory back before its solves; the next :func:`patch_features` loads the CNN
    again (about 0.04–0.15 s for the ONNX session). The ``torchiid decompose`` command calls
    this after the last image's Stage 0. An :class:`OnnxFeatureExtractor` made by the caller
    keeps its own session.
    """
    _default_onnx.cache_clear()
    _torch_extractor.cache_clear()
    onnx_backend.release_sessions()


class PatchFeatureExtractor(nn.Module):
    """Module twin of :func:`patch_features` with the torch backend (for larger models).

    The backbone is a registered submodule, so ``.to(device)`` moves it; gradients flow to the
    image if it requires them (the backbone's parameters are frozen).

    Args:
        mode: ``"shared"`` or ``"crop"``.
        size: patch side in pixels.
        stride: grid step in pixels.
        scale: shared-mode resize factor.
        batch_size: crop-mode patches per forward pass.
        pretrained: load the ImageNet weights.

    Shape:
        ``(B, 3, H, W)`` linear RGB -> :class:`PatchFeatures` with ``(B, N, 1280)`` features.
    """

    def __init__(
        self,
        mode: str = "shared",
        size: int = 60,
        stride: int = 30,
        scale: float = 2.0,
        batch_size: int = 32,
        pretrained: bool = True,
    ) -> None:
        super().__init__()
        if mode not in ("shared", "crop"):
            raise ParameterError(f"mode must be 'shared' or 'crop', got {mode!r}")
        self.mode, self.size, self.stride = mode, size, stride
        self.scale, self.batch_size = scale, batch_size
        self.extractor = FeatureMapExtractor(efficientnet_lite0(pretrained)).requires_grad_(False)
        self.extractor.eval()

    def train(self, mode: bool = True) -> PatchFeatureExtractor:
        """Set training mode; the frozen backbone always stays in eval mode (fixed BN)."""
        super().train(mode)
        self.extractor.eval()
        return self

    def forward(self, image: torch.Tensor) -> PatchFeatures:
        """Patch features of a linear-RGB batch; see :func:`patch_features`."""
        grid = _check_args(image, self.size, self.stride, self.mode, self.scale, self.batch_size)
        feats = _compute(image, grid, self.extractor, self.mode, self.scale, self.batch_size, False)
        return PatchFeatures(grid, feats.to(image.dtype), self.mode)
