"""The base of carto's domain vocabularies (verdicts, algorithms, search paths): an Enum whose members are the strings
they name.

Python 3.11's ``str``-mixed Enum prints as ``Class.MEMBER`` in f-strings and ``str()``; carto's reports, CSV and JSON
have always written the bare name (``ok``, ``gmapping``), so these print as their value. They compare and hash as
that string, so a value read back from a file (a plain ``str``) equals its member.
"""
from __future__ import annotations

import enum

__all__ = ["TextEnum"]


class TextEnum(str, enum.Enum):
    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)
