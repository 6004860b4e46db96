"""What `carto relocalize` chooses from a map.carto itself: score thresholds scaled to the map's own score level."""
import math

import numpy as np
import pytest
from reloc_map import pose_error, with_walls

from carto_cli.relocalization import Relocalizer
from carto_cli.relocalization.auto import REFERENCE_LEVEL, choose_for_map, score_level


def _reference_level(loaded) -> float:
    """Every node's points at its local pose in every submap holding it, cell by cell (unknown reads 0.1)."""
    scores = []
    for s, nodes in enumerate(loaded.submap_nodes):
        grid = loaded.submaps[s].grid
        for n in nodes:
            x, y, th = loaded.node_local_poses[n]
            values = []
            for px, py in loaded.node_points[n]:
                wx, wy = x + math.cos(th) * px - math.sin(th) * py, y + math.sin(th) * px + math.cos(th) * py
                cell = np.floor((np.array([[wx, wy]]) - grid.origin) / grid.resolution).astype(np.int64)
                p = grid.probability(cell)[0]
                values.append(0.1 if np.isnan(p) else p)
            scores.append(np.mean(values))
    return float(np.median(scores))


def test_score_level_is_the_median_of_the_nodes_scores_where_they_were_inserted(mapped):
    assert len(mapped.node_points) < 200  # every node is sampled: the reference takes them all
    assert score_level(mapped) == pytest.approx(_reference_level(mapped), abs=1e-9)


def test_a_map_with_faint_walls_gets_lower_thresholds_and_its_right_answers(mapped, queries):
    """Walls seen a few times each, as a key scan every metre leaves them (0.9 -> 0.62): the map's own scans score
    about what they do in carto's map of aces' key scans (0.58-0.6), and the stock thresholds lose its right answers
    (2 of 39 global queries answered when written), the scaled ones find them without a wrong one (27)."""
    _, qs = queries
    weak = with_walls(mapped, lambda p: 0.5 + 0.3 * (p - 0.5))
    level = score_level(weak)
    assert level < 0.8 * REFERENCE_LEVEL
    auto = choose_for_map(weak.options, weak)
    ro, stock = auto.options.relocalization, weak.options.relocalization
    k = level / REFERENCE_LEVEL
    assert ro.global_min_score == pytest.approx(stock.global_min_score * k, abs=1e-3)
    assert ro.min_score == pytest.approx(stock.min_score * k, abs=1e-3)
    assert "relocalization.global_min_score" in auto.describe()

    def right(relocalizer) -> tuple[int, int]:
        good = wrong = 0
        for scan, ref in qs:
            res = relocalizer.relocalize(scan)
            if res.verdict == "ok":
                e = pose_error(res.pose, ref)
                good += e[0] < 0.2 and e[1] < 2.0
                wrong += not (e[0] < 0.2 and e[1] < 2.0)
        return good, wrong

    stock_right, _ = right(Relocalizer(weak))
    auto_right, auto_wrong = right(Relocalizer(weak, auto.options))
    assert auto_wrong == 0
    assert auto_right >= stock_right + len(qs) // 2


def test_a_sharp_map_keeps_its_thresholds(mapped):
    sharp = with_walls(mapped, lambda p: np.full_like(p, 0.9))  # every wall as a dense recording leaves it
    assert score_level(sharp) >= REFERENCE_LEVEL
    auto = choose_for_map(sharp.options, sharp)
    assert auto.options == sharp.options and auto.settings == ()
