"""Errors a user can act on.

Anything raised as a ``CartoError`` is reported as one line on stderr with exit
status 2; anything else is an internal error (exit status 1).
"""
from __future__ import annotations

from pathlib import Path


class CartoError(Exception):
    """A problem with the user's input, reported without a traceback."""

    def __init__(self, message: str, path: str | Path | None = None):
        super().__init__(message)
        self.message = message
        self.path = None if path is None else str(path)

    def __str__(self) -> str:
        if self.path:
            return f"{self.path}: {self.message}"
        return self.message


class FormatError(CartoError):
    """The file is not in a format carto reads, or is truncated or corrupt."""


class TopicError(CartoError):
    """A topic is missing, ambiguous or of an unsupported type."""
