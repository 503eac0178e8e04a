"""The decomposition of one image of a collection, with its iteration bar."""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable
from typing import Any

import torch

from torchiid.collection.settings import RunSettings
from torchiid.core.exceptions import ConvergenceWarning

__all__ = ["run_method"]


def run_method(
    decompose_fn: Callable[..., Any],
    batch: torch.Tensor,
    mask: torch.Tensor | None,
    settings: RunSettings,
    stem: str,
    *,
    show_progress: bool = False,
    release_models: bool = False,
) -> Any:
    """``decompose_fn`` on one image with the run's parameters and what its files need.

    Args:
        decompose_fn: :func:`torchiid.model.decompose` or a function of the same signature.
        batch: the ``(1, 3, H, W)`` image.
        mask: its ``(1, 1, H, W)`` mask, or ``None``.
        settings: the run's settings (parameters, whether every alternation is kept).
        stem: the image's name, for the iteration bar.
        show_progress: show an iteration bar on stderr.
        release_models: give back the CNN's memory once the image's Stage 0 is done
            (:func:`~torchiid.features.patches.release_feature_extractors`).

    Returns:
        What ``decompose_fn`` returns; a solve that stops at its cap warns nothing here (the
        image's one-line note and ``-info.json`` report it).
    """
    from tqdm import tqdm

    params = settings.params
    it_bar = tqdm(
        total=params.iterations,
        desc=f"{stem}",
        unit="it",
        disable=not show_progress,
        file=sys.stderr,
        leave=False,
    )

    def progress(stage: str, k: int, total: int) -> None:
        if stage == "iteration":
            it_bar.update(1)
        elif stage == "features" and release_models:
            # no image left for the CNN: its memory goes back before the solves
            from torchiid.features import patches

            patches.release_feature_extractors()

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            return decompose_fn(
                batch,
                params,
                mask=mask,
                return_iterations=settings.save_iterations,
                return_stage1=True,  # sigma.exr
                progress=progress,
            )
    finally:
        it_bar.close()
