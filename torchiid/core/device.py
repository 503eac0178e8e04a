"""Choosing the torch device a computation runs on."""

from __future__ import annotations

import torch

from torchiid.core.exceptions import TorchiidError

__all__ = ["resolve_device"]


def resolve_device(name: str) -> torch.device:
    """The device for a ``--device`` choice.

    Args:
        name: ``auto`` (CUDA when available, else CPU), ``cpu``, ``cuda`` or any name
            :class:`torch.device` accepts.

    Returns:
        The device.

    Raises:
        TorchiidError: ``cuda`` was asked for but no CUDA device is available.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise TorchiidError("--device cuda was asked for, but no CUDA device is available")
    return torch.device(name)
