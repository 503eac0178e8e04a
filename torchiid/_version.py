"""The version of torchiid: the one place it is written (``pyproject.toml`` reads it here)."""

__version__ = "1.0.0"
