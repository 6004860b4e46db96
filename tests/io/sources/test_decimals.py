"""io.sources.decimals: the numbers of a line, bit for bit as numpy's own parser (the reference) reads them."""
import gzip

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import shared_path

from carto_cli.io.sources.decimals import decimals


def _same(text: str) -> None:
    try:
        expected = np.fromstring(text, sep=" ")
    except ValueError:
        with pytest.raises(ValueError):
            decimals(text)
        return
    got = decimals(text)
    assert got.dtype == expected.dtype and got.tobytes() == expected.tobytes(), text


@pytest.mark.parametrize("text", [
    "1.65 81.91 -2.356194 0.013090 30.0 0.01 0 360",  # a laser line's kind of numbers
    "-0 -0.0 +3.25 .5 -.5 7. 007.100",  # signs, bare dots, leading zeros
    "123456789012345 1234567890123456 99999999999999.9 0.1234567890123456789",  # 15 digits and beyond
    "0.0000000000000000000001 0.00000000000000000000001 1e5 -2.5E-3",  # 10**22 and beyond, exponents
    "nan -inf inf", "", "   ", "\t3.5\n", " 1  2\t3 \r\n",  # numpy's words, nothing, any whitespace
    "1.2.3", "abc", "12-3", "4 x 5", "1,5",  # not numbers: numpy's error
])
def test_the_cases_a_log_holds_and_the_ones_left_to_numpy(text):
    _same(text)


_number = st.builds(
    lambda sign, whole, frac, digits: f"{sign}{whole}" + (f".{frac:0{digits}d}" if digits else ""),
    st.sampled_from(["", "-", "+"]), st.integers(0, 10**18), st.integers(0, 10**12), st.integers(0, 24))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(_number, st.floats(allow_nan=False).map(repr)), max_size=40),
       st.sampled_from([" ", "  ", "\t", " \n "]))
def test_random_decimals_read_as_numpy_reads_them(numbers, sep):
    _same(sep.join(numbers))


@pytest.mark.slow_without_jit
def test_every_laser_line_of_a_real_log():
    path = shared_path("bench", "freiburg-079", "scans.clf.gz")
    with gzip.open(path, "rt", encoding="latin-1") as f:
        payloads = [line.split(None, 1)[1].rsplit(None, 3)[0] for line in f if line.startswith("FLASER")]
    assert len(payloads) > 4000
    for text in payloads:
        _same(text)


def test_plain_decimals_never_reach_numpy(monkeypatch):
    """The point of the kernel: a log's numbers are read without numpy's parser."""
    import carto_cli.io.sources.decimals as module

    monkeypatch.setattr(module.np, "fromstring", lambda *a, **k: pytest.fail("numpy parsed a plain line"))
    assert decimals(" 1.65 -0.001068\t360 +7. .5 0\n").tolist() == [1.65, -0.001068, 360.0, 7.0, 0.5, 0.0]
