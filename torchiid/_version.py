"""The version of torchiid, as the running code reports it (``pyproject.toml`` holds the same)."""

__version__ = "1.16.1"
