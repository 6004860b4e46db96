"""Constraint builder pieces: the fixed-ratio sampler and the option choosing the fast matcher,
with the node and submap handed to it as plain data (it never sees the pose graph)."""
from __future__ import annotations

import numpy as np

from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.mapping.constraint_builder import ConstraintBuilder, FixedRatioSampler, NodeData, SubmapData
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
            return branch_and_bound.MatchResult(False, 0.0, np.asarray(estimate, dtype=np.float64))
        return matcher

    monkeypatch.setattr(branch_and_bound, "match", fake("match"))
    monkeypatch.setattr(branch_and_bound, "match_multilevel", fake("multilevel"))
    node = NodeData(index=0, trajectory=0, global_pose=np.zeros(3), points=np.ones((10, 2)))
    submap = SubmapData(index=0, trajectory=0, grid=ProbabilityGrid(0.05, (0.0, 0.0), (8, 8)),
                        local_pose=np.zeros(3), global_pose=np.zeros(3))

    for flag, expected in (("false", "match"), ("true", "multilevel")):
        options = load_options(None, [f"pose_graph.constraint_builder.fast_correlative_scan_matcher.multilevel={flag}"])
        builder = ConstraintBuilder(options)
        assert builder.search(node, submap) is None
        assert calls[-1] == expected
        # The pair passes the candidate rules (same trajectory, no distance, first pulse) and is searched.
        assert builder.maybe_add(node, submap) is None
        assert calls[-1] == expected and builder.stats.candidates == 1 and builder.stats.searched == 2
