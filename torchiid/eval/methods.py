"""The methods an evaluation run scores: the paper's method and the reference baselines."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import torch

import torchiid.model
from torchiid.baselines.result import BaselineResult
from torchiid.baselines.retinex import color_retinex
from torchiid.baselines.trivial import reflectance_is_image, shading_is_image
from torchiid.core.exceptions import ParameterError
from torchiid.params import Parameters

__all__ = ["BASELINES", "METHODS", "method_parameters", "run_method"]

METHODS = ("semantic", "retinex", "r=i", "s=i")
"""``semantic``: the paper's method (:func:`torchiid.model.decompose`); the others are
:data:`BASELINES`."""

BASELINES: dict[str, Callable[..., BaselineResult]] = {
    "retinex": color_retinex,
    "r=i": reflectance_is_image,
    "s=i": shading_is_image,
}
"""The baseline methods, each called as ``fn(image, mask=mask)``."""


def check_method(method: str) -> None:
    """Raise :class:`ParameterError` unless ``method`` is one of :data:`METHODS`."""
    if method not in METHODS:
        raise ParameterError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")


def run_method(
    method: str,
    image: torch.Tensor,
    mask: torch.Tensor | None = None,
    params: Parameters | None = None,
) -> Any:
    """Decompose ``image`` with one of :data:`METHODS`.

    Args:
        method: ``"semantic"`` (:func:`torchiid.model.decompose`), ``"retinex"``,
            ``"r=i"`` or ``"s=i"`` (:data:`BASELINES`).
        image: linear RGB ``(B, 3, H, W)``.
        mask: ``(B, 1, H, W)`` bool pixels to decompose, or ``None`` for all.
        params: parameters of ``semantic`` (default: the ``default`` preset); ignored by
            the baselines.

    Returns:
        An object with ``reflectance`` ``(B, 3, H, W)`` and ``shading`` ``(B, 1, H, W)``,
        linear: a :class:`torchiid.model.Decomposition` or a
        :class:`~torchiid.baselines.BaselineResult`.

    Raises:
        ParameterError: unknown ``method``.
        TorchiidError: the method failed on this input.
    """
    if method in BASELINES:
        return BASELINES[method](image, mask=mask)
    check_method(method)
    return torchiid.model.decompose(image, params, mask=mask)


def method_parameters(method: str, params: Parameters | None = None) -> dict[str, Any]:
    """The parameters a method runs with, as recorded in ``summary.json``.

    Args:
        method: one of :data:`METHODS` (anything else has no parameters).
        params: parameters of ``semantic`` (default: the ``default`` preset).

    Returns:
        ``semantic``: ``params.to_dict()``; ``retinex``: the defaults of
        :func:`~torchiid.baselines.color_retinex`; otherwise ``{}``.
    """
    if method == "semantic":
        return (params if params is not None else Parameters.preset("default")).to_dict()
    if method == "retinex":
        sig = inspect.signature(color_retinex).parameters.values()
        return {
            p.name: p.default
            for p in sig
            if p.default is not inspect.Parameter.empty and p.name != "mask"
        }
    return {}
