"""Turning whatever a decoding library raises into one FormatError that names the file."""
from __future__ import annotations

import contextlib
import traceback
from pathlib import Path

from carto_cli.core.errors import CartoError, FormatError


def describe_exception(e: BaseException) -> str:
    """A one-line account of a library failure; bare asserts get the failing source line."""
    text = str(e).strip()
    if isinstance(e, KeyError) and e.args:
        text = f"unknown key {e.args[0]!r}"
    if text:
        return text.splitlines()[0]
    frames = traceback.extract_tb(e.__traceback__)
    if frames:
        last = frames[-1]
        line = (last.line or "").strip()
        what = "consistency check failed" if isinstance(e, AssertionError) else type(e).__name__
        return f"{what} in {last.name}: {line}" if line else f"{what} in {last.name}"
    return type(e).__name__


def with_path(e: CartoError, path: Path) -> CartoError:
    """The same error naming ``path`` (messages.py cannot know which file a message came from)."""
    return type(e)(e.message, path)


@contextlib.contextmanager
def translate_errors(path: Path, what: str):
    """Re-raise library failures as ``FormatError('corrupt or truncated WHAT: ...', path)``.

    Readers fail in many ways on bad input (asserts, struct errors, KeyErrors, sqlite
    errors...), and none of those is something a user can act on as it stands.
    """
    try:
        yield
    except CartoError as e:
        if e.path is not None:
            raise
        raise with_path(e, path) from e
    except Exception as e:
        raise FormatError(f"corrupt or truncated {what}: {describe_exception(e)}", path) from e
