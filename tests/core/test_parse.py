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


def test_laser_poses_one_unnamed_or_each_by_topic():
    assert parse.laser_poses(["1,2,90deg"], "--laser-pose") == pytest.approx((1.0, 2.0, math.pi / 2))
    poses = parse.laser_poses(["/front=0.3,0,0", "back=-0.3, 0, 180deg"], "--laser-pose")
    assert set(poses) == {"/front", "back"} and poses["back"] == pytest.approx((-0.3, 0.0, math.pi))


@pytest.mark.parametrize("bad, message", [
    (["1,2,3", "4,5,6"], "several poses need their lasers' topics"),
    (["/a=1,2,3", "4,5,6"], "give every laser's pose as TOPIC=x,y,yaw"),
    (["=1,2,3"], "a topic is missing"),
    (["/a=1,2,3", "/a=1,2,3"], "/a given twice"),
    (["/a=1,2"], "--laser-pose /a: expected x,y,yaw"),
])
def test_laser_poses_errors_say_what_to_give(bad, message):
    with pytest.raises(CartoError, match=message):
        parse.laser_poses(bad, "--laser-pose")
