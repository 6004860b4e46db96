"""Whitespace-separated decimal numbers from text, as a kernel: the bulk of reading a CARMEN log.

``np.fromstring(text, sep=" ")`` took about half of the time reading a log took (docs/scaling.md). Nearly every
number in a log is a plain decimal (``1.65``, ``-0.001068``), which this kernel converts exactly as a correctly
rounded parser does: with at most 15 significant digits the digits form an integer that a double holds exactly,
and ``10**k`` (k <= 22) is exact too, so their quotient is the double nearest the decimal (Clinger's fast path).
Anything else (exponents, ``nan``, more digits, stray characters) is left to numpy, whose answer is then the one
used; so the values are the same bit for bit.
"""
from __future__ import annotations

import numpy as np
from numba import njit

_POW10 = np.array([10.0**k for k in range(23)])  # each exactly representable


@njit(cache=True, nogil=True)
def _space(c: int) -> bool:
    return c == 32 or 9 <= c <= 13


@njit(cache=True, nogil=True)
def _parse(buf: np.ndarray, out: np.ndarray, pow10: np.ndarray) -> int:
    """The numbers in ``buf`` (ASCII bytes) into ``out``; their count, or -1 outside the fast path."""
    n = 0
    i = 0
    size = buf.size
    while True:
        while i < size and _space(buf[i]):
            i += 1
        if i >= size:
            return n
        negative = buf[i] == 45
        if negative or buf[i] == 43:
            i += 1
        mantissa = 0
        significant = 0
        digits = 0
        fraction = 0
        dot = False
        while i < size:
            c = int(buf[i])  # not uint8 arithmetic: the mantissa would wrap at 256
            if 48 <= c <= 57:
                digits += 1
                if mantissa != 0 or c != 48:
                    significant += 1
                    if significant > 15:
                        return -1
                mantissa = mantissa * 10 + (c - 48)
                if dot:
                    fraction += 1
            elif c == 46 and not dot:
                dot = True
            else:
                break
            i += 1
        if digits == 0 or fraction > 22 or (i < size and not _space(buf[i])) or n >= out.size:
            return -1
        value = float(mantissa) / pow10[fraction]
        out[n] = -value if negative else value
        n += 1


def decimals(text: str) -> np.ndarray:
    """The whitespace-separated numbers of ``text``, as ``np.fromstring(text, sep=" ")`` reads them (which
    raises ValueError on a token that is not a number)."""
    buf = np.frombuffer(text.encode("latin-1"), dtype=np.uint8)
    out = np.empty(buf.size // 2 + 1)
    n = _parse(buf, out, _POW10)
    if n <= 0:  # outside the fast path, or nothing to read: numpy's answer, errors included
        return np.fromstring(text, sep=" ")
    return out[:n]
