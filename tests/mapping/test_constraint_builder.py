"""Constraint builder pieces: the fixed-ratio sampler and the option choosing the fast matcher."""
from __future__ import annotations

import numpy as np

from carto_cli.mapping.constraint_builder import ConstraintBuilder, FixedRatioSampler
from carto_cli.matching import branch_and_bound
from carto_cli.options import load_options


def test_fixed_ratio_sampler_fires_on_the_requested_share_evenly():
    s = FixedRatioSampler(0.3)
    fired = [s.pulse() for _ in range(100)]
    assert sum(fired) == 30
    assert fired[0]  # the first pulse fires, as in Cartographer
    gaps = np.diff(np.flatnonzero(fired))
    assert gaps.max() <= 4


def test_multilevel_option_selects_the_coarse_to_fine_matcher(monkeypatch):
    calls = []

    def fake(name):
        def matcher(stack, points, estimate, **kw):
            calls.append(name)
            return branch_and_bound._not_found(estimate)
        return matcher

    monkeypatch.setattr(branch_and_bound, "match", fake("match"))
    monkeypatch.setattr(branch_and_bound, "match_multilevel", fake("multilevel"))

    class Entry:
        local_pose = np.zeros(3)
        global_pose = np.zeros(3)
        trajectory = 0

        class submap:
            grid = None

    class Graph:
        submaps = [Entry()]
        node_points = [np.ones((10, 2))]
        node_trajectory = [0]
        global_poses = np.zeros((1, 3))

    for flag, expected in (("false", "match"), ("true", "multilevel")):
        options = load_options(None, [f"pose_graph.constraint_builder.fast_correlative_scan_matcher.multilevel={flag}"])
        builder = ConstraintBuilder(options)
        builder._stacks[0] = object()  # no grid needed: the matcher is faked
        assert builder.search(Graph(), 0, 0) is None
        assert calls[-1] == expected
