"""The parts a relocalization query goes through (relocalization/stages.py, judge.py, map_index.py, search.py)."""
import dataclasses
import math

import numpy as np
import pytest

from carto_cli.relocalization.judge import Candidate
from carto_cli.relocalization.relocalizer import Relocalizer
from carto_cli.relocalization.result import SearchPath, Timings
from carto_cli.relocalization.stages import Carry


def test_a_query_is_frozen_and_reading_its_prior_makes_a_new_one(relocalizer, queries):
    _, qs = queries
    scan, truth = qs[4]
    search, fine = relocalizer.preprocess(scan)
    q = relocalizer.stages.query(relocalizer.laser_pose, search, fine, corridor=False, max_jump=None,
                                 second_look=True, jobs=1)
    carry = Carry(Timings())
    with_prior = relocalizer.stages.with_prior(q, carry, truth, 0.3, math.radians(5))
    assert q.prior is None and not q.filtered
    assert with_prior.reliable and with_prior.filtered and np.allclose(with_prior.prior, truth)
    with pytest.raises(dataclasses.FrozenInstanceError):
        with_prior.prior = None  # type: ignore[misc]
    # The stages answer it as Relocalizer.relocalize does.
    r = relocalizer.stages.run(with_prior, carry)
    assert r.path == SearchPath.WINDOWED and r.success


def test_the_relocalizer_is_a_small_face_over_its_parts(relocalizer):
    methods = [n for n, v in vars(Relocalizer).items() if callable(v) and not n.startswith("__")]
    assert len(methods) < 20
    assert relocalizer.judge.index is relocalizer.index and relocalizer.searches.index is relocalizer.index
    assert relocalizer.searches.cache is relocalizer.cache is relocalizer.judge.cache


def test_a_candidate_is_frozen():
    c = Candidate(0, np.zeros(3), 0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.score = 1.0  # type: ignore[misc]
