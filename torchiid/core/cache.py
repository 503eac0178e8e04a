"""Keys identifying the inputs of cached intermediate results."""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["InputKey", "input_key"]


class _TensorPart(NamedTuple):
    tensor: torch.Tensor
    version: object
    stride: tuple[int, ...]
    offset: int


class InputKey:
    """Identity of a computation's inputs, for the stage caches.

    Tensors match only when they are the *same tensor objects* (not merely equal storage
    addresses: a freed tensor's memory can be reused by a new one), with the same strides and
    unmodified in place since (``_version``); other items match by ``==``. The key holds strong
    references to its tensors, so their memory cannot be recycled while a cache entry lives.
    Inference tensors (``torch.inference_mode``) have no version counter: keys holding one
    never match, so nothing computed from them is reused.
    """

    __slots__ = ("_parts",)

    def __init__(self, *items: object) -> None:
        parts: list[object] = []
        for it in items:
            if isinstance(it, torch.Tensor):
                version = object() if it.is_inference() else it._version
                parts.append(_TensorPart(it, version, tuple(it.stride()), int(it.storage_offset())))
            else:
                parts.append(it)
        self._parts = tuple(parts)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, InputKey) or len(other._parts) != len(self._parts):
            return False
        for a, b in zip(self._parts, other._parts, strict=True):
            if isinstance(a, _TensorPart) or isinstance(b, _TensorPart):
                if not (isinstance(a, _TensorPart) and isinstance(b, _TensorPart)):
                    return False
                if a.tensor is not b.tensor or a.version != b.version:
                    return False
                if a.stride != b.stride or a.offset != b.offset:
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]  # compared, never hashed


def input_key(*items: object) -> InputKey:
    """The :class:`InputKey` of ``items`` (tensors and plain values).

    >>> x = torch.zeros(3)
    >>> k = input_key(x, 0.5)
    >>> k == input_key(x, 0.5), k == input_key(x, 0.6), k == input_key(x.clone(), 0.5)
    (True, False, False)
    >>> _ = x.add_(1)
    >>> k == input_key(x, 0.5)
    False
    """
    return InputKey(*items)
