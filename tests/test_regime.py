"""regime: the survey `--profile auto` runs before mapping, and the settings it chooses."""
import math

import numpy as np
import pytest

from carto_cli.io.topics import select_topics
from carto_cli.options import load_options
from carto_cli.pipeline import Auto, Configured, MapRequest, resolve
from carto_cli.regime import Regime, choose, survey
from carto_cli.sim import Lidar, follow_route, loop_building, loop_trajectory, office, simulate


@pytest.fixture(scope="module")
def world():
    return loop_building()


def _survey(sim, **kw):
    rec = sim.recording()
    return survey(rec, select_topics(rec), **kw), rec


def test_a_10hz_recording_with_odometry_is_dense_and_gets_the_wheeled_profile(world):
    sim = simulate(world, loop_trajectory(world), duration=20.0, lidar=Lidar(beams=180))
    regime, _ = _survey(sim)
    assert regime.motion_source == "odometry" and regime.odometry
    assert not regime.sparse and regime.step_median < 0.1
    assert regime.scan_rate == pytest.approx(10.0, rel=1e-6)
    assert regime.beams == 180 and regime.fov == pytest.approx(1.5 * math.pi, abs=0.05)
    assert regime.no_return is None  # the simulated laser reports "no return" as inf
    choice = choose(regime)
    assert choice.profile == "wheeled" and choice.settings == []
    marked = Regime(**{**vars(regime), "no_return": 30.0})
    assert "trajectory_builder_2d.max_range=29.900" in choose(marked).settings


def test_key_scans_are_recognised_by_motion_not_by_timestamps(world):
    # One scan every 2 s of driving, stamped 1 ms apart in the log's own clock would read as 1000 Hz;
    # here the robot moves ~1 m between scans, which is what decides.
    sim = simulate(world, loop_trajectory(world), duration=60.0, scan_rate=0.5, odom_rate=0.5, lidar=Lidar(beams=180))
    regime, _ = _survey(sim)
    assert regime.sparse and regime.step_median > 0.25
    # With odometry, key scans go to GMapping (docs/gmapping.md), its range set below the no-return reading.
    choice = choose(regime)
    assert choice.algorithm == "gmapping" and choice.profile == "sparse"
    assert "algorithm gmapping" in choice.describe()
    assert not any("motion_scaled_prior" in s for s in choice.settings)  # Cartographer's matcher is not used
    # The simulated odometry errs by a few percent of the travel (2 % scale, 2 cm per sqrt(m)): measured, and the
    # particle filter's motion noise sized to it, well below slam_gmapping's 0.1 m per m.
    assert regime.odometry_error is not None and 0.005 < regime.odometry_error < 0.08
    assert "off the scans by" in regime.describe()
    srr = float(next(s for s in choice.settings if s.startswith("gmapping.srr=")).split("=")[1])
    assert srr == pytest.approx(max(0.02, 1.5 * regime.odometry_error / math.sqrt(2 * math.log(2))), rel=1e-3)
    # A user's --algorithm cartographer gets Cartographer's key-scan settings.
    forced = choose(regime, algorithm="cartographer")
    assert forced.algorithm == "cartographer" and forced.profile == "sparse"
    assert any("motion_scaled_prior=true" in s for s in forced.settings)
    assert not any(s.startswith("gmapping.") for s in forced.settings)
    assert len(forced.reasons) >= len(forced.settings) - 1


def test_without_odometry_the_motion_comes_from_scan_matching():
    # Key scans without odometry are not covered: one-scan grids underestimate a 0.6 m step along a
    # corridor by a factor of 3 (see the issue 12 note); a 10 Hz recording is measured within a factor 2.
    world = office()
    sim = simulate(world, follow_route(world), duration=60.0, odom_rate=0.0, lidar=Lidar(beams=180))
    regime, _ = _survey(sim, max_scans=100)
    assert not regime.odometry and regime.motion_source == "scan matching"
    gt = sim.ground_truth[:100]
    true_step = np.median(np.hypot(np.diff(gt[:, 1]), np.diff(gt[:, 2])))
    # One-scan grids match short of the full step along corridors (0.53 m for 0.91 m here): good enough
    # to tell the regimes apart, which is all the survey uses it for.
    assert true_step / 2 < regime.step_median < 1.5 * true_step
    assert choose(regime).profile == "office"
    assert choose(regime).algorithm == "cartographer"  # GMapping needs odometry


def test_the_motion_noise_follows_the_measured_odometry_error_within_bounds():
    base = dict(scans=10, beams=180, fov=math.pi, range_max=80.0, no_return=None, odometry=True, imu=False,
                motion_source="odometry", step_median=1.0, step_p90=1.2, turn_median=0.2, turn_p90=0.5,
                scan_rate=1000.0)

    def noise(error):
        settings = choose(Regime(**base, odometry_error=error)).settings
        return {s.split("=")[0]: float(s.split("=")[1]) for s in settings if s.startswith("gmapping.s")}

    assert noise(None) == {}  # not measured: GMapping's own defaults stay
    good = noise(0.025)  # the benchmark buildings' odometry
    scale = 1.5 * 0.025 / math.sqrt(2 * math.log(2)) / 0.1
    assert good == pytest.approx({"gmapping.srr": 0.1 * scale, "gmapping.srt": 0.2 * scale,
                                  "gmapping.str": 0.1 * scale, "gmapping.stt": 0.2 * scale}, rel=1e-3)
    assert noise(0.0)["gmapping.srr"] == pytest.approx(0.02)  # never below a fifth of the defaults
    assert noise(5.0)["gmapping.srr"] == pytest.approx(0.2)  # nor above twice them
    # srr is the measure itself; the other three keep their ratio to it from the base noise (a user's --set
    # gmapping.srr=0.05 doubles them)
    other = choose(Regime(**base, odometry_error=0.025), gmapping_noise=(0.05, 0.2, 0.1, 0.2)).settings
    assert f"gmapping.srr={0.1 * scale:.4g}" in other and f"gmapping.srt={0.4 * scale:.4g}" in other


def test_no_return_marker_needs_many_identical_top_readings():
    from carto_cli.regime import no_return_value

    rng = np.random.default_rng(0)
    real = rng.uniform(0.5, 20.0, 10_000)
    assert no_return_value(real) is None  # the largest real reading is not a marker
    marked = np.concatenate([real, np.full(200, 81.83)])
    assert no_return_value(marked) == pytest.approx(81.83)


def test_describe_says_what_was_detected():
    r = Regime(scans=10, beams=180, fov=math.pi, range_max=80.0, no_return=50.0, odometry=True, imu=False,
               motion_source="odometry", step_median=1.0, step_p90=1.2, turn_median=0.2, turn_p90=0.5,
               scan_rate=1000.0)
    text = r.describe()
    assert text.startswith("key scans") and "1.00 m" in text and "no return = 50 m" in text and "odometry" in text


def test_configure_layers_the_users_overrides_over_the_auto_choice(world):
    sim = simulate(world, loop_trajectory(world), duration=10.0, lidar=Lidar(beams=90))
    rec = sim.recording()
    sel = select_topics(rec)
    got = resolve(MapRequest(rec, Auto(("trajectory_builder_2d.max_range=12.5",))), rec, sel).configured
    assert got.auto is not None and got.auto.profile == "wheeled"
    assert got.options.trajectory_builder_2d.max_range == 12.5  # --set wins over the derived 29.9
    assert got.options == load_options("wheeled", got.auto.settings + ["trajectory_builder_2d.max_range=12.5"])
    named = load_options("office")
    assert resolve(MapRequest(rec, named), rec, sel).configured == Configured(named)


def test_several_lasers_map_with_cartographer_and_a_velocity_over_uneven_windows():
    key_scans = dict(scans=10, beams=180, fov=math.pi, range_max=30.0, no_return=None, odometry=True, imu=False,
                     motion_source="odometry", step_median=1.0, step_p90=1.2, turn_median=0.2, turn_p90=0.5,
                     scan_rate=1.0)
    assert choose(Regime(**key_scans)).algorithm == "gmapping"  # one laser's key scans: the particle filter
    merged = choose(Regime(**key_scans, lasers=("/front", "/back")))
    assert merged.algorithm == "cartographer" and merged.chose_algorithm
    assert "trajectory_builder_2d.pose_extrapolator.constant_velocity.pose_queue_duration=0.2" in merged.settings
    assert "2 lasers merged (/front, /back)" in Regime(**key_scans, lasers=("/front", "/back")).describe()
