"""One photo opened in the app: its decomposition, kept to edit it without recomputing.

:func:`open_photo` reads a file with the loader the CLI uses (EXIF orientation, bit depth,
validation), checks the memory it will take, runs :func:`torchiid.decompose` with a progress
callback, and keeps what the page needs: the full-resolution layers (for the downloads) and
the same layers at the preview resolution (for the edits, which run on them at every slider
move). Nothing here imports Gradio.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchiid.app.objects import Objects
from torchiid.core.exceptions import ImageError, InputWarning, MemoryLimitError
from torchiid.core.first_compile import COMPILING, notify_first_compile
from torchiid.io import load_image
from torchiid.io.decode import declared_size
from torchiid.io.layers import srgb8_from_linear
from torchiid.model import Decomposition, check_memory, decompose
from torchiid.params import Parameters
from torchiid.pipeline.results import solve_record
from torchiid.resample import downsample, working_size

__all__ = ["PREVIEW_SIDE", "Layers", "Session", "open_photo", "srgb8", "view_shading"]

#: the longest side of the previews: the working resolution, or this when that is larger
PREVIEW_SIDE = 1024

#: ``progress(fraction, message)``, as the page's progress bar takes it
ProgressFn = Callable[[float, str], None]


@dataclass(frozen=True)
class Layers:
    """A decomposition's layers at one resolution, ``(1, C, h, w)`` linear, on the CPU.

    Attributes:
        image: the photo ``I``.
        reflectance: Stage 2's ``R``.
        shading: Stage 2's gray ``S``.
        sigma: the last Stage 1 shading ``σ``.
        rho: the last Stage 1 reflectance ``ρ``.
        mask: ``(1, 1, h, w)`` bool from the photo's alpha channel, or ``None``.
    """

    image: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor
    sigma: torch.Tensor
    rho: torch.Tensor
    mask: torch.Tensor | None = None

    @property
    def size(self) -> tuple[int, int]:
        """``(h, w)``."""
        return int(self.image.shape[-2]), int(self.image.shape[-1])


@dataclass
class Session:
    """What one browser tab holds of its photo.

    Attributes:
        name: the uploaded file's name (its stem names the output files).
        full: the layers at the photo's resolution, exactly as :func:`torchiid.decompose`
            returned them.
        preview: the same layers at the preview resolution (the working resolution, at most
            :data:`PREVIEW_SIDE`): ``reflectance · shading == image`` there too.
        result: the decomposition (layers dropped: they are in ``full``), for its report.
        params: the parameters it ran with.
        objects: the object proposals under which a click selects a region.
        gallery: every alternation's layers as ``(sRGB uint8 image, caption)``.
        info: sizes, seconds and the solvers' reports.
        orientation: the EXIF orientation that was applied.
        cache: merged layers and loaded textures, computed once per session.
    """

    name: str
    full: Layers
    preview: Layers
    result: Decomposition
    params: Parameters
    objects: Objects | None
    gallery: list[tuple[np.ndarray, str]]
    info: dict[str, Any]
    orientation: int = 1
    cache: dict[Any, Any] = field(default_factory=dict)

    @property
    def stem(self) -> str:
        """The output files' stem."""
        return Path(self.name).stem or "photo"


def srgb8(x: torch.Tensor) -> np.ndarray:
    """``(1, C, h, w)`` or ``(C, h, w)`` linear values as an ``(h, w, 3)`` uint8 sRGB image."""
    x = x[0] if x.dim() == 4 else x
    return srgb8_from_linear(x.detach().float().cpu().expand(3, -1, -1))


def view_shading(shading: torch.Tensor, white: float | None = None) -> torch.Tensor:
    """A shading divided by its 99th percentile (or ``white``), as the CLI's ``-shading.png``."""
    if white is None:
        y = shading.detach().float().mean(-3).flatten()
        y = y[:: max(1, y.numel() // 1_000_000)]  # a quantile needs no more than a megapixel
        white = float(torch.quantile(y, 0.99))
    return shading / (white if white > 0 else 1.0)


def _preview_layers(full: Layers, size: tuple[int, int]) -> Layers:
    """``full`` area-averaged to ``size``, with ``R = I / S`` and ``ρ = I / σ`` there.

    Dividing the averaged photo by the averaged shading (rather than averaging the
    reflectance) keeps ``R · S == I`` at the preview resolution, so an edit that changes
    nothing shows the photo itself.
    """
    image = downsample(full.image, size)
    shading = downsample(full.shading, size)
    sigma = downsample(full.sigma, size)
    mask = None
    if full.mask is not None:
        mask = downsample(full.mask.float(), size) > 0.5

    def ratio(s: torch.Tensor) -> torch.Tensor:
        r = torch.where(s > 0, image / s.clamp_min(1e-12), torch.zeros_like(image))
        return r.clamp(0, 1) if mask is None else r.clamp(0, 1) * mask

    return Layers(image, ratio(shading), shading, sigma, ratio(sigma), mask)


def _gallery(result: Decomposition) -> list[tuple[np.ndarray, str]]:
    """Every alternation's ``σ, ρ, R, S`` (working resolution) as captioned sRGB images."""
    items = []
    for k, it in enumerate(result.iterations, start=1):
        items += [
            (srgb8(view_shading(it.sigma)), f"{k}: Stage 1 shading σ"),
            (srgb8(it.rho), f"{k}: Stage 1 reflectance ρ"),
            (srgb8(it.reflectance), f"{k}: Stage 2 reflectance R"),
            (srgb8(view_shading(it.shading)), f"{k}: Stage 2 shading S"),
        ]
    return items


def _info(name: str, loaded: Any, result: Decomposition, params: Parameters, seconds: float):
    """The run's record: sizes, seconds, the solvers' reports (as the CLI's ``-info.json``)."""
    h, w = loaded.image.shape[-2:]
    wh, ww = result.working_size or (h, w)
    return {
        "input": name,
        "method": "semantic",
        "size": [int(w), int(h)],
        "working_size": [int(ww), int(wh)],
        "exif_orientation": loaded.orientation,
        "bit_depth": loaded.bit_depth,
        "negatives_set_to_zero": loaded.negatives,
        "iterations": params.iterations,
        "shading_white": float(result.shading_white[0]),
        **solve_record(result, params, seconds, result.times),
    }


def _app_terms(message: str) -> str:
    """A memory message in the page's terms: its controls, not the command line's options."""
    message = message.replace(
        f"--max-side {Parameters().output.max_side}, the default (max_side in Python)",
        f"a working resolution of {Parameters().output.max_side} px",
    )
    cut = message.find("; set TORCHIID_MEMORY_CHECK=0")
    if cut >= 0:  # the server's environment, which the page cannot set
        message = message[:cut] + "; a photo of fewer pixels needs less"
    return message


def _check_working_size(name: str, h: int, w: int, params: Parameters) -> None:
    """Refuse, in the page's terms, a working resolution too small for the method's patches."""
    side = params.output.max_side
    patch = params.features.patch_size
    wh, ww = working_size(h, w, side)
    if min(wh, ww) >= patch:
        return
    needed = -(-patch * max(h, w) // min(h, w))  # the longer side that gives patch px
    fix = (
        f"set the working resolution to {needed} px or more, or to 0 (the photo's own size)"
        if needed <= max(h, w)
        else "it is too narrow for the method at any working resolution"
    )
    raise ImageError(
        f"{name}: at a working resolution of {side} px the photo is {ww}x{wh} px, under the "
        f"{patch} px the method needs on each side; {fix}"
    )


def open_photo(
    path: str | Path,
    params: Parameters,
    *,
    name: str | None = None,
    device: torch.device | str = "cpu",
    memory_limit: int | None = None,
    progress: ProgressFn | None = None,
) -> Session:
    """Read, check and decompose one photo.

    Args:
        path: the file (anything :func:`torchiid.io.load_image` reads).
        params: the parameters (preset, alternations, working resolution).
        name: the name the user knows the file by (default: the file's name).
        device: where the decomposition runs; the layers are kept on the CPU.
        memory_limit: a cap in bytes on the memory the decomposition may take (CPU only;
            ``None``: only what is available, and ``TORCHIID_MEMORY_LIMIT``).
        progress: called with the fraction done and what is being done: before Stage 0,
            after it and after each alternation (the model's progress callback), and before
            the full-resolution layers.

    Returns:
        the :class:`Session`.

    Raises:
        ImageError: the file cannot be used (the message names it).
        MemoryLimitError: the photo would take more memory than the cap or what is left.
    """
    t0 = time.perf_counter()
    say = progress or (lambda fraction, message: None)
    name = name or Path(path).name
    say(0.0, "reading the photo")
    device = torch.device(device)
    flags = {"return_stage1": True, "return_iterations": True}

    def check(h: int, w: int) -> None:
        if device.type == "cpu":
            try:
                check_memory(h, w, params, limit=memory_limit, **flags)
            except MemoryLimitError as exc:
                raise MemoryLimitError(f"{name}: {_app_terms(str(exc))}") from None

    size = declared_size(path)  # before decoding: a small file may declare a huge picture
    if size is not None:
        check(*size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # the info below says it
        loaded = load_image(path)
    h, w = loaded.image.shape[-2:]
    check(h, w)
    _check_working_size(name, h, w, params)
    total = params.iterations + 2  # Stage 0, the alternations, the full-resolution layers
    say(0.0, "Stage 0: semantic features")

    done = [0.0]  # the fraction the bar shows

    def step(stage: str, k: int, of: int) -> None:
        done[0] = (1 + k) / total
        if stage == "features":
            say(done[0], f"alternation 1 of {of}")
        elif k < of:
            say(done[0], f"alternation {k + 1} of {of}")
        else:
            say(done[0], "full-resolution layers")

    mask = None if loaded.mask is None else loaded.mask[None].to(device)
    with notify_first_compile(lambda: say(done[0], COMPILING)):
        result = decompose(
            loaded.image[None].to(device),
            params,
            mask=mask,
            progress=step,
            return_features=True,
            **flags,
        )
    cpu = [x.cpu() for x in (result.reflectance, result.shading, result.sigma, result.rho)]
    full = Layers(loaded.image[None], *cpu, None if loaded.mask is None else loaded.mask[None])
    wh, ww = result.working_size
    preview = _preview_layers(full, working_size(wh, ww, PREVIEW_SIDE))
    objects = Objects.from_features(result.features)
    if objects is None:  # the parameters' priors did not need the proposals
        objects = Objects.from_image(downsample(full.image, (wh, ww)))
    gallery = _gallery(result)
    kept = dataclasses.replace(
        result,
        features=None,
        iterations=(),
        **{k: None for k in ("reflectance", "shading", "sigma", "rho")},
    )
    seconds = time.perf_counter() - t0
    return Session(
        name=name,
        full=full,
        preview=preview,
        result=kept,
        params=params,
        objects=objects,
        gallery=gallery,
        info=_info(name, loaded, result, params, seconds),
        orientation=loaded.orientation,
    )
