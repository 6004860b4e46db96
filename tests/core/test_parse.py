import math

import pytest

from carto_cli.core import parse
from carto_cli.core.errors import CartoError


def test_pose_accepts_commas_spaces_and_degrees():
    assert parse.pose("1.5,-2,90deg", "--laser-pose") == pytest.approx((1.5, -2.0, math.pi / 2))
    assert parse.pose(" 1 2 0.5 ", "--laser-pose") == (1.0, 2.0, 0.5)


@pytest.mark.parametrize("bad", ["1,2", "a,2,3", "1,2,3rad", "1,2,inf", "nan,0,0", "1,2,3,4"])
def test_pose_errors_name_the_option(bad):
    with pytest.raises(CartoError, match="^--laser-pose: "):
        parse.pose(bad, "--laser-pose")


def test_megabytes_reads_sizes_people_type():
    assert parse.megabytes("512", "--memory-budget") == 512.0
    assert parse.megabytes("1GB", "--memory-budget") == 1024.0
    assert parse.megabytes("1.5g", "--memory-budget") == 1536.0
    assert parse.megabytes("256 MB", "--memory-budget") == 256.0
    assert parse.megabytes("2048KB", "--memory-budget") == 2.0


@pytest.mark.parametrize("bad", ["", "lots", "-1GB", "0", "1TB"])
def test_megabytes_errors_name_the_option(bad):
    with pytest.raises(CartoError, match="--memory-budget"):
        parse.megabytes(bad, "--memory-budget")
