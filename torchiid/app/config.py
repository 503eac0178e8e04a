"""What a server's decompositions use and what its page starts with."""

from __future__ import annotations

from dataclasses import dataclass

from torchiid.params import Parameters

__all__ = ["AppConfig"]


@dataclass(frozen=True)
class AppConfig:
    """How a server runs its decompositions and what the page starts with.

    Attributes:
        preset: the preset the page starts with.
        iterations: the alternations it starts with (``None``: the preset's).
        max_side: the working resolution it starts with (``None``: the preset's).
        device: where decompositions run (``"cpu"``, ``"cuda"``, ...).
        memory_limit: a cap in bytes on one decomposition's memory (``None``: what is
            available, and ``TORCHIID_MEMORY_LIMIT``).
    """

    preset: str = "default"
    iterations: int | None = None
    max_side: int | None = None
    device: str = "cpu"
    memory_limit: int | None = None

    def params(self) -> Parameters:
        """The parameters the page starts with."""
        params = Parameters.preset(self.preset)
        if self.iterations is not None:
            params = params.replace(iterations=self.iterations)
        if self.max_side is not None:
            params = params.replace(max_side=self.max_side)
        return params
