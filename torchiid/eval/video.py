"""Temporal consistency of a decomposed video: the warping error of Lai et al. (ECCV 2018).

For consecutive frames ``t − 1, t`` with optical flow ``F = F_{t−1→t}`` on frame ``t − 1``'s
pixels and its non-occlusion mask ``M`` (1 where the pixel is still visible in frame ``t``),

    E_t = (1 / Σ_i M(i)) · Σ_i M(i) · ‖R_{t−1}(i) − warp(R_t, F)(i)‖²,

the squared difference summed over the three channels and averaged over the non-occluded
pixels; ``warp(R_t, F)(i) = R_t(i + F(i))`` (bilinear) brings frame ``t``'s reflectance onto
frame ``t − 1``. The sequence's error is the mean of ``E_t`` over its pairs. As in Lai et al.'s
code the values are the frames as shown, **8-bit sRGB scaled to [0, 1]** (``space="srgb"``, the
default: what a viewer of the reflectance video sees; ``space="linear"`` scores the linear
albedo instead). ``M`` is the forward–backward check of the flows
(:func:`~torchiid.video.flow.occlusion_mask`, α = 0.01, β = 0.5 as in Lai et al.) or a given
occlusion map.

Flows come from the **input frames** (OpenCV DIS, both directions; or Farnebäck), or from
given ground-truth files: Middlebury ``.flo`` (:func:`read_flo`), named after frame ``t − 1``
as in MPI Sintel (``flow/<scene>/frame_0002.flo`` is the flow from frame 2 to frame 3). The
occluded pixels of frame ``t − 1`` (white) come from a folder of PNG maps matched by frame
number (:func:`occlusion_index`; MPI Sintel's ``occlusions/<scene>/frame_0002.png``), else
from ``<stem>-occlusions.png`` or ``occlusions_0002.png`` next to the ``.flo`` file
(:func:`occlusion_file`; the latter is the layout of the shared ``sintel-clean`` sample, not
Sintel's own), else the given flow is checked against the estimated backward flow.

A flow estimated on the frames is not independent of a video method that itself follows
estimated flow: when both use the same estimator the warping error partly measures agreement
with that flow. Ground-truth flow, or another estimator (``method="farneback"`` against a
method that used DIS), is the fair comparison.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchiid.core.colour import linear_to_srgb
from torchiid.core.exceptions import ImageError, ParameterError, ShapeError
from torchiid.io import load_image
from torchiid.video.flow import estimate_flow, occlusion_mask, warp

__all__ = [
    "FLO_TAG",
    "read_flo",
    "write_flo",
    "pair_warping_error",
    "WarpingError",
    "warping_error",
    "occlusion_file",
    "occlusion_index",
    "frame_number",
    "read_occlusions",
    "VideoPair",
    "evaluate_video",
]

#: the float32 tag at the start of a Middlebury ``.flo`` file ("PIEH")
FLO_TAG = 202021.25


def read_flo(path: str | os.PathLike) -> torch.Tensor:
    """Read a Middlebury ``.flo`` optical-flow file.

    Layout: the float32 tag 202021.25, int32 width, int32 height, then ``width · height · 2``
    float32 ``(u, v)``, row-major, little-endian.

    Returns:
        ``(1, 2, H, W)`` float32 flow ``(u, v)``.

    Raises:
        ImageError: the file is missing, unreadable, not a ``.flo`` file, truncated, or holds
            NaN values (Sintel marks unknown flow by huge values, which are kept).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) < 12:
        raise ImageError(f"{path}: not a Middlebury .flo file (only {len(data)} bytes)")
    tag, width, height = struct.unpack("<fii", data[:12])
    if tag != FLO_TAG:
        raise ImageError(f"{path}: not a Middlebury .flo file (tag {tag!r}, expected {FLO_TAG})")
    if not (0 < width < 1 << 16 and 0 < height < 1 << 16):
        raise ImageError(f"{path}: bad .flo size {width}x{height}")
    need = 12 + 8 * width * height
    if len(data) < need:
        raise ImageError(f"{path}: truncated .flo file ({len(data)} of {need} bytes)")
    arr = np.frombuffer(data, dtype="<f4", count=2 * width * height, offset=12)
    arr = arr.reshape(height, width, 2)
    if np.isnan(arr).any():
        raise ImageError(f"{path}: flow contains NaN values")
    return torch.from_numpy(arr.transpose(2, 0, 1).astype(np.float32))[None]


def write_flo(path: str | os.PathLike, flow: torch.Tensor) -> Path:
    """Write ``(1, 2, H, W)`` or ``(2, H, W)`` flow as a Middlebury ``.flo`` file."""
    f = flow[0] if flow.dim() == 4 else flow
    if f.dim() != 3 or f.shape[0] != 2:
        raise ShapeError(f"expected a (2, H, W) flow, got {tuple(flow.shape)}")
    _, h, w = f.shape
    path = Path(path)
    arr = f.detach().to("cpu", torch.float32).permute(1, 2, 0).contiguous().numpy()
    path.write_bytes(struct.pack("<fii", FLO_TAG, w, h) + arr.astype("<f4").tobytes())
    return path


def _space(x: torch.Tensor, space: str) -> torch.Tensor:
    if space == "linear":
        return x.clamp(0, 1)
    if space == "srgb":
        return linear_to_srgb(x.clamp(0, 1))
    raise ParameterError(f"space must be 'srgb' or 'linear', got {space!r}")


def pair_warping_error(
    first: torch.Tensor,
    second: torch.Tensor,
    flow: torch.Tensor,
    valid: torch.Tensor,
    space: str = "srgb",
) -> float:
    """``E`` of one pair: frame ``t − 1`` (``first``) against ``second`` warped onto it.

    Args:
        first: ``(1, 3, H, W)`` linear layer of frame ``t − 1``.
        second: ``(1, 3, H, W)`` linear layer of frame ``t``.
        flow: ``(1, 2, H, W)`` flow from frame ``t − 1`` to ``t``.
        valid: ``(1, 1, H, W)`` bool, the non-occluded pixels of frame ``t − 1``.
        space: ``"srgb"`` (default) or ``"linear"`` values, clipped to [0, 1].

    Returns:
        The mean over valid pixels of the channel-summed squared difference (``nan`` when no
        pixel is valid).

    Example:
        >>> r = torch.rand(1, 3, 16, 16)
        >>> f = torch.zeros(1, 2, 16, 16)
        >>> valid = torch.ones(1, 1, 16, 16, dtype=torch.bool)
        >>> pair_warping_error(r, r, f, valid) < 1e-12  # no motion, no change
        True
        >>> round(pair_warping_error(r, 0 * r, f, valid, space="linear"), 3) == round(
        ...     float(r.square().sum(1).mean()), 3)
        True
    """
    a, b = _space(first.float(), space), _space(second.float(), space)
    if a.shape != b.shape or a.dim() != 4:
        raise ShapeError(f"frames differ: {tuple(first.shape)} and {tuple(second.shape)}")
    warped, inside = warp(b, flow.to(b.device, b.dtype))
    m = valid.to(b.device).bool() & inside
    n = int(m.sum())
    if n == 0:
        return float("nan")
    d = (a - warped).square().sum(1, keepdim=True)
    return float(d[m].double().sum() / n)


@dataclass(frozen=True)
class WarpingError:
    """Warping error of a sequence.

    Attributes:
        pairs: ``E_t`` of every consecutive pair ``(t − 1, t)``, in order (``nan`` where no
            pixel was valid).
        mean: mean of the finite ``E_t``.
        valid: share of non-occluded pixels of every pair.
        sources: where each pair's flow came from: ``"estimated"`` or ``"given"``.
    """

    pairs: tuple[float, ...]
    mean: float
    valid: tuple[float, ...]
    sources: tuple[str, ...]


def warping_error(
    layers: Sequence[torch.Tensor],
    frames: Sequence[torch.Tensor] | None = None,
    *,
    flows: Sequence[torch.Tensor | None] | None = None,
    occlusions: Sequence[torch.Tensor | None] | None = None,
    space: str = "srgb",
    method: str = "dis",
) -> WarpingError:
    """Warping error (Lai et al. 2018) of a sequence of layers (see the module notes).

    Args:
        layers: ``T`` linear layers ``(1, 3, H, W)`` or ``(3, H, W)`` (the reflectance).
        frames: the ``T`` input frames (linear RGB, same size), from which the flows are
            estimated where none is given.
        flows: optional ``T − 1`` flows ``F_{t−1→t}`` ``(1, 2, H, W)`` (``None`` entries:
            estimated).
        occlusions: optional ``T − 1`` bool maps ``(1, 1, H, W)``, True where a pixel of frame
            ``t − 1`` is occluded in frame ``t`` (used with the given flows; ``None`` entries:
            the forward–backward check).
        space: ``"srgb"`` or ``"linear"``.
        method: the flow estimator.

    Returns:
        :class:`WarpingError`.
    """
    seq = [x[None] if x.dim() == 3 else x for x in layers]
    count = len(seq)
    if frames is not None:
        frames = [x[None] if x.dim() == 3 else x for x in frames]
        if len(frames) != count:
            raise ShapeError(f"{count} layers but {len(frames)} frames")
    flows = list(flows) if flows is not None else [None] * max(count - 1, 0)
    occlusions = list(occlusions) if occlusions is not None else [None] * max(count - 1, 0)
    if len(flows) != max(count - 1, 0) or len(occlusions) != len(flows):
        raise ShapeError(f"{count} frames need {count - 1} flows and occlusion maps")
    pairs, shares, sources = [], [], []
    for t in range(1, count):
        fw, occ = flows[t - 1], occlusions[t - 1]
        source = "estimated" if fw is None else "given"
        bw = None
        if fw is None or occ is None:
            if frames is None:
                raise ShapeError("the frames are needed to estimate flows")
            bw = estimate_flow(frames[t], frames[t - 1], method)
        if fw is None:
            fw = estimate_flow(frames[t - 1], frames[t], method)
        if occ is None:
            valid = occlusion_mask(fw, bw)
        else:
            valid = ~occ.bool()
        shares.append(float(valid.float().mean()))
        pairs.append(pair_warping_error(seq[t - 1], seq[t], fw, valid, space))
        sources.append(source)
    finite = [e for e in pairs if np.isfinite(e)]
    mean = float(np.mean(finite)) if finite else float("nan")
    return WarpingError(tuple(pairs), mean, tuple(shares), tuple(sources))


# --------------------------------------------------------------------------- results folders


def _frame_digits(stem: str) -> str | None:
    digits = ""
    for ch in reversed(stem):
        if not ch.isdigit():
            break
        digits = ch + digits
    return digits or None


def frame_number(name: str, position: int) -> int:
    """The number of a frame file: the digits ending its stem, else ``position``.

    ``frame_0002.png``: 2; ``position`` is the frame's 1-based place in the sequence.
    """
    digits = _frame_digits(Path(name).stem)
    return int(digits) if digits is not None else position


def occlusion_index(folder: str | os.PathLike) -> dict[int, Path]:
    """The occlusion maps of a folder by frame number.

    Every ``.png`` whose stem ends in digits (``frame_0002.png``, ``occlusions_0002.png``:
    frame 2) is the map of frame ``t − 1``'s pixels occluded in frame ``t`` (white). Other
    files are ignored.

    Raises:
        ImageError: the folder cannot be listed, holds no such map, or two maps for a frame.
    """
    folder = Path(folder)
    try:
        files = sorted(q for q in folder.iterdir() if q.suffix.lower() == ".png" and q.is_file())
    except OSError as exc:
        raise ImageError(f"{folder}: cannot list ({exc.strerror or exc})") from None
    index: dict[int, Path] = {}
    for f in files:
        digits = _frame_digits(f.stem)
        if digits is None:
            continue
        n = int(digits)
        if n in index:
            raise ImageError(
                f"{folder}: two occlusion maps for frame {n}: {index[n].name}, {f.name}"
            )
        index[n] = f
    if not index:
        raise ImageError(f"{folder}: holds no occlusion maps (.png files named ..._NNNN.png)")
    return index


def occlusion_file(flow_dir: Path, stem: str) -> Path | None:
    """The occlusion map of frame ``stem`` next to its ``.flo`` file in ``flow_dir``, or ``None``.

    Looked for as ``<stem>-occlusions.png``, then as ``occlusions_<NNNN>.png`` (``NNNN``: the
    digits ending the stem; the layout of the shared ``sintel-clean`` sample, ``gt/``). MPI
    Sintel itself keeps them in a folder of their own, ``occlusions/<scene>/frame_NNNN.png``:
    see :func:`occlusion_index`.
    """
    candidates = [flow_dir / f"{stem}-occlusions.png"]
    digits = _frame_digits(stem)
    if digits is not None:
        candidates.append(flow_dir / f"occlusions_{digits}.png")
    for c in candidates:
        if c.is_file():
            return c
    return None


@dataclass(frozen=True)
class VideoPair:
    """The scores of one pair of consecutive frames.

    Attributes:
        first: name of frame ``t − 1``.
        second: name of frame ``t``.
        estimated: warping error of the reflectance with the estimated flow.
        estimated_valid: share of non-occluded pixels (forward–backward check).
        given: warping error with the given flow (``None`` without a ``.flo`` file).
        given_valid: share of non-occluded pixels of the given occlusions (``None``).
        input_estimated: warping error of the input frames themselves (estimated flow), the
            reference for "no flicker beyond the video's own".
        flow_file: the ``.flo`` file used, or ``None``.
        input_given: warping error of the input frames with the given flow (``None``).
        occlusion_file: the occlusion map used with the given flow, or ``None`` (none given:
            the forward–backward check).
    """

    first: str
    second: str
    estimated: float
    estimated_valid: float
    given: float | None
    given_valid: float | None
    input_estimated: float
    flow_file: str | None
    input_given: float | None = None
    occlusion_file: str | None = None


def evaluate_video(
    frames: Sequence[torch.Tensor],
    reflectances: Sequence[torch.Tensor],
    names: Sequence[str],
    *,
    flow_dir: str | os.PathLike | None = None,
    space: str = "srgb",
    method: str = "dis",
    occlusions: str | os.PathLike | dict[int, Path] | None = None,
    numbers: Sequence[int] | None = None,
) -> list[VideoPair]:
    """Warping errors of every consecutive pair (module notes), estimated and given flows.

    Args:
        frames: the ``T`` input frames, linear ``(3, H, W)`` or ``(1, 3, H, W)``.
        reflectances: the ``T`` reflectances, same sizes.
        names: the frames' file names (their stems name the ``.flo`` files of ``flow_dir``).
        flow_dir: folder of ground-truth flows ``<stem of frame t − 1>.flo`` (the flow from
            frame ``t − 1`` to ``t``) and occlusion maps (:func:`occlusion_file`), or ``None``.
        space: ``"srgb"`` (default) or ``"linear"``.
        method: the flow estimator (``"dis"`` or ``"farneback"``).
        occlusions: a folder of occlusion maps matched to frame ``t − 1`` by frame number
            (:func:`occlusion_index`, or its result), used with the given flows instead of
            the maps of ``flow_dir``; a pair without a map there gets the forward–backward
            check.
        numbers: the frames' numbers for ``occlusions`` (default: :func:`frame_number` of
            each name and its 1-based position).

    Returns:
        One :class:`VideoPair` per pair.

    Raises:
        ImageError: a ``.flo`` or occlusion file cannot be read or has another size.
    """
    frames = [x[None] if x.dim() == 3 else x for x in frames]
    refl = [x[None] if x.dim() == 3 else x for x in reflectances]
    if not len(frames) == len(refl) == len(names):
        raise ShapeError(f"{len(frames)} frames, {len(refl)} reflectances, {len(names)} names")
    if numbers is None:
        numbers = [frame_number(n, i + 1) for i, n in enumerate(names)]
    if occlusions is not None and not isinstance(occlusions, dict):
        occlusions = occlusion_index(occlusions)
    pairs = []
    for t in range(1, len(frames)):
        a, b = frames[t - 1], frames[t]
        if refl[t].shape[-2:] != a.shape[-2:] or refl[t - 1].shape[-2:] != a.shape[-2:]:
            raise ShapeError(
                f"{names[t]}: the reflectance is {tuple(refl[t].shape[-2:])}, the frame "
                f"{tuple(a.shape[-2:])}"
            )
        fw = estimate_flow(a, b, method)
        bw = estimate_flow(b, a, method)
        valid = occlusion_mask(fw, bw)
        est = pair_warping_error(refl[t - 1], refl[t], fw, valid, space)
        inp = pair_warping_error(a, b, fw, valid, space)
        given = given_valid = flow_file = input_given = occ = None
        if flow_dir is not None:
            stem = Path(names[t - 1]).stem
            path = Path(flow_dir) / f"{stem}.flo"
            if path.is_file():
                gt = read_flo(path)
                if gt.shape[-2:] != a.shape[-2:]:
                    h, w = a.shape[-2:]
                    raise ImageError(
                        f"{path}: flow is {gt.shape[-1]}x{gt.shape[-2]} but the frames are {w}x{h}"
                    )
                if occlusions is not None:
                    occ = occlusions.get(numbers[t - 1])
                else:
                    occ = occlusion_file(Path(flow_dir), stem)
                if occ is not None:
                    gvalid = ~read_occlusions(occ, tuple(a.shape[-2:]))
                else:
                    gvalid = occlusion_mask(gt, bw)
                given = pair_warping_error(refl[t - 1], refl[t], gt, gvalid, space)
                input_given = pair_warping_error(a, b, gt, gvalid, space)
                given_valid = float(gvalid.float().mean())
                flow_file = str(path)
        pairs.append(
            VideoPair(
                Path(names[t - 1]).name,
                Path(names[t]).name,
                est,
                float(valid.float().mean()),
                given,
                given_valid,
                inp,
                flow_file,
                input_given,
                None if occ is None else str(occ),
            )
        )
    return pairs


def read_occlusions(path: str | os.PathLike, shape: tuple[int, int]) -> torch.Tensor:
    """An occlusion map (white, any channel above half: occluded) as ``(1, 1, H, W)`` bool.

    Raises:
        ImageError: the file cannot be read or is not ``shape`` ``(H, W)``.
    """
    img = load_image(path, linear=True, alpha="ignore", min_side=1).image
    if tuple(img.shape[-2:]) != tuple(shape):
        raise ImageError(
            f"{path}: occlusion map is {img.shape[-1]}x{img.shape[-2]} but the frames are "
            f"{shape[1]}x{shape[0]}"
        )
    return (img.amax(0) > 0.5)[None, None]
