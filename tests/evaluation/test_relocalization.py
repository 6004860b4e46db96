"""The relocalization evaluation harness on the simulated loop-building map (tests/reloc_map.py): probes
judged against their references, refusals, the query limit, scan picking, and the summary."""
import math

import numpy as np
import pytest
from reloc_map import build_map, second_pass

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.evaluation.relocalization import (
    Outcome,
    Probe,
    every_nth_scan,
    pose_error,
    run_probes,
    scans_by_index,
    summarize_outcomes,
    within,
)
from carto_cli.relocalization import RelocalizationResult, Relocalizer

TOLERANCE = (0.2, math.radians(2.0))


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    mapped = build_map(tmp_path_factory.mktemp("map"))
    sim, qs = second_pass(mapped)
    return Relocalizer(mapped), sim, qs


def test_pose_error_is_measured_in_the_reference_frame_with_wrapped_heading():
    exy, eyaw = pose_error((1.0, 2.0, math.pi / 2), (1.0, 2.3, math.pi / 2 + 0.05))
    assert exy == pytest.approx(0.3) and eyaw == pytest.approx(0.05)
    # Across the +-pi seam the heading error is the short way round.
    assert pose_error((0.0, 0.0, math.pi - 0.01), (0.0, 0.0, -math.pi + 0.01))[1] == pytest.approx(0.02)
    assert within((0.0, 0.0, 0.0), (0.1, -0.1, 0.02), TOLERANCE)
    assert not within((0.0, 0.0, 0.0), (0.1, -0.1, 0.04), TOLERANCE)
    assert not within((0.0, 0.0, 0.0), (0.2, 0.1, 0.0), TOLERANCE)


def test_probes_are_judged_against_their_references(setup):
    reloc, _, qs = setup
    (s0, t0), (s1, t1), (s2, t2) = qs[3], qs[10], qs[20]
    probes = [Probe(3, s0, t0 + [0.5, -0.3, 0.1], t0, 0.5, math.radians(5)),
              Probe(10, s1, None, t1),  # global
              # A right answer judged against a reference 1 m off: claimed, but a false match.
              Probe(20, s2, t2 + [0.3, 0.0, 0.0], t2 + [1.0, 0.0, 0.0], 0.5, math.radians(5))]
    out = run_probes(reloc, probes, tolerance=TOLERANCE)
    assert [o.probe for o in out] == probes
    assert [o.claimed for o in out] == [True, True, True]
    assert [o.correct for o in out] == [True, True, False]
    assert [o.ok for o in out] == [True, True, False]
    assert out[0].error_xy < 0.1 and out[0].error_yaw < math.radians(1)
    assert out[2].error_xy == pytest.approx(1.0, abs=0.1)
    assert (out[0].error_xy, out[0].error_yaw) == pose_error(t0, out[0].result.pose)
    s = summarize_outcomes(out)
    assert (s.queries, s.successes, s.claimed, s.false_matches, s.refused) == (3, 2, 3, 1, 0)
    assert s.success_rate == pytest.approx(2 / 3)
    assert [o.result.path for o in out] == ["windowed", "global", "windowed"]
    assert list(s.paths.items()) == [("windowed", 2), ("global", 1)]  # in order of appearance
    ms = [o.ms for o in out]
    assert s.latency.max_ms == max(ms) and s.latency.mean_ms == pytest.approx(np.mean(ms))
    assert s.latency.p50_ms == pytest.approx(np.median(ms))


class _Answers:
    """A stand-in relocalizer that answers every scan with the pose (and verdict) it was given for it."""

    def __init__(self, answers):
        self.answers = answers

    def relocalize(self, scan, prior, sigma_xy=None, sigma_yaw=None, context=None):
        pose, success = self.answers[scan]
        return RelocalizationResult(np.asarray(pose, float), 0.7, "windowed", success, [0], {}, 1.0 + scan)


def test_answers_are_correct_within_the_tolerance_inclusive():
    ref = np.array([2.0, 1.0, math.pi / 2])
    # In the reference's frame: 0.2 m ahead (on the limit), 0.21 m aside, 1.9 degrees, 2.1 degrees; and one
    # right answer the relocalizer did not claim.
    answers = {0: (transform.compose(ref, (0.2, 0.0, 0.0)), True),
               1: (transform.compose(ref, (0.0, 0.21, 0.0)), True),
               2: (transform.compose(ref, (0.0, 0.0, math.radians(1.9))), True),
               3: (transform.compose(ref, (0.0, 0.0, math.radians(-2.1))), True),
               4: (ref, False)}
    out = run_probes(_Answers(answers), [Probe(k, k, None, ref) for k in range(5)],
                     tolerance=(0.2 + 1e-12, math.radians(2.0)))
    assert [o.correct for o in out] == [True, False, True, False, True]
    assert [o.ok for o in out] == [True, False, True, False, False]
    assert out[1].error_xy == pytest.approx(0.21) and out[3].error_yaw == pytest.approx(math.radians(2.1))
    s = summarize_outcomes(out)
    assert (s.successes, s.claimed, s.false_matches) == (2, 4, 2)
    assert s.latency.p50_ms == 3.0 and s.latency.max_ms == 5.0


def test_without_a_reference_the_relocalizers_verdict_is_taken(setup):
    reloc, _, qs = setup
    scan, truth = qs[5]
    out = run_probes(reloc, [Probe(5, scan, truth + [0.3, 0.3, 0.0])])
    assert out[0].correct is None and out[0].error_xy is None and out[0].ok == out[0].claimed is True
    with pytest.raises(ValueError, match="tolerance"):
        run_probes(reloc, [Probe(5, scan, truth, truth)])


def test_refusals_are_errors_unless_recorded(setup):
    reloc, _, qs = setup
    scan, truth = qs[5]
    far = Probe(5, scan, (500.0, 500.0, 0.0), truth)
    with pytest.raises(CartoError, match="from the nearest submap"):
        run_probes(reloc, [far], tolerance=TOLERANCE)
    out = run_probes(reloc, [far, Probe(5, scan, truth, truth)], tolerance=TOLERANCE, record_refusals=True)
    assert out[0].result is None and "from the nearest submap" in out[0].refusal
    assert not out[0].claimed and not out[0].ok and out[0].ms is None and out[0].correct is None
    assert out[1].ok
    s = summarize_outcomes(out)
    assert (s.queries, s.successes, s.refused, s.false_matches) == (2, 1, 1, 0)
    assert s.success_rate == 0.5 and sum(s.paths.values()) == 1 and s.latency.max_ms == out[1].ms


def test_the_query_limit_stops_reading_the_probes(setup):
    reloc, _, qs = setup
    pulled = []

    def probes():
        for k, (scan, truth) in enumerate(qs):
            pulled.append(k)
            yield Probe(k, scan, truth, None, 0.2, math.radians(3))

    out = run_probes(reloc, probes(), max_queries=2)
    assert len(out) == 2 and pulled == [0, 1]


def test_scans_are_picked_by_index_in_the_given_order_or_every_nth(setup):
    _, sim, _ = setup
    rec = sim.recording()
    picked = scans_by_index(rec, [30, 4, 30])
    assert [i for i, _ in picked] == [30, 4, 30]
    assert picked[0][1].time == pytest.approx(1006.0) and picked[1][1].time == pytest.approx(1000.8)
    with pytest.raises(CartoError, match="beyond the recording's 350 scans"):
        scans_by_index(rec, [400])
    nth = list(every_nth_scan(rec, 100))
    assert [i for i, _ in nth] == [0, 100, 200, 300]
    assert nth[1][1].time == pytest.approx(1020.0)


def test_summary_of_nothing():
    s = summarize_outcomes([])
    assert (s.queries, s.successes, s.success_rate, s.paths) == (0, 0, 0.0, {})
    assert s.latency.p50_ms is None and s.latency.max_ms is None


def test_outcome_of_a_refusal_has_no_time():
    o = Outcome(Probe(0, None), None, refusal="no returns")
    assert o.ms is None and not o.claimed and not o.ok
