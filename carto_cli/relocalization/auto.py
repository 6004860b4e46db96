"""``carto relocalize`` with no profile: settings chosen from the map and the scans, as ``carto map`` chooses its own.

A map.carto carries the options it was built with (chosen by ``--profile auto`` when it was mapped): the scans are
filtered as they were then. What it cannot carry is how well a right answer scores in it, and that differs from map
to map: a score is the mean probability under the scan's points, and a wall seen a hundred times (a dense
recording) reads 0.9 where one seen a few times (a key scan every metre) reads 0.55-0.65. The score thresholds
(``min_score``, ``global_min_score``, ``global_search_min_score``) were set on dense maps; on a sparse one right
answers score below them (``carto map`` on aces' key scans, then ``carto relocalize``: right answers at 0.47-0.61,
two of 25 global queries answered). :func:`choose_for_map` measures the map's own level -- the median score of its
nodes' scans where they were inserted into their submaps (:func:`score_level`) -- and scales the thresholds by
level / ``REFERENCE_LEVEL`` where the map is below the maps the thresholds were set on (never above: a sharper map
keeps them). The own scan is in its submap, so the level reads a little high (0.02-0.04 on the dense maps, 0.06 on
a key-scan map, against later scans' right answers): the scaling errs on the strict side. What it costs -- more
wrong answers claimed for scans taken off the mapped route -- is measured in docs/localization.md.

A map_server image carries neither options nor scans (its walls read 0.9 like a dense map's), so the scans
decide what the defaults cannot know: a laser that reports "no return" as a fixed reading at the top of its
range (the dense benchmarks' 30 m, a Hokuyo's 5.6 m) would put phantom points on a circle at that range, so the
range is cut just below it, as mapping does (``regime.no_return_value``); a sensor that reaches less than the
default range keeps its own limit.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from carto_cli.core.records import Scan
from carto_cli.matching.scoring import score_at
from carto_cli.options import Options
from carto_cli.regime import no_return_value

__all__ = ["LEVEL_NODES", "REFERENCE_LEVEL", "AutoRelocalization", "choose_for_map", "choose_for_scans",
           "score_level"]

# The score level of the maps the thresholds were set on: the median of score_level over the dense benchmark
# maps (bench/relocalization.py, mapped by auto: dense-aces 0.739, dense-intel 0.770, dense-freiburg-079 0.803).
REFERENCE_LEVEL = 0.77
LEVEL_NODES = 200  # nodes sampled (evenly along the map's node ids) for the level: 30-60 ms on the bench maps
MIN_LEVEL_NODES = 10  # fewer nodes with points say too little: the thresholds stay


@dataclasses.dataclass(frozen=True)
class AutoRelocalization:
    options: Options
    settings: tuple[str, ...]  # 'key=value' of what was changed
    reasons: tuple[str, ...]

    def describe(self) -> str:
        if not self.settings:
            return "defaults (nothing in the map or the scans calls for other settings)"
        groups: dict[str, list[str]] = {}
        for setting, reason in zip(self.settings, self.reasons):
            groups.setdefault(reason, []).append(setting)
        return "; ".join(f"{', '.join(settings)} ({reason})" for reason, settings in groups.items())


def choose_for_scans(options: Options, scans: Sequence[Scan]) -> AutoRelocalization:
    """``options`` with the trajectory builder's range limits fitted to ``scans`` (module doc)."""
    tb = options.trajectory_builder_2d
    if not scans:
        return AutoRelocalization(options, (), ())
    ranges = np.concatenate([np.asarray(s.ranges, dtype=np.float64) for s in scans])
    max_range = tb.max_range
    settings: list[str] = []
    reasons: list[str] = []
    no_return = no_return_value(ranges)
    if no_return is not None and no_return <= max_range + 0.05:
        max_range = max(no_return - 0.1, tb.min_range + 0.1)
        settings.append(f"trajectory_builder_2d.max_range={max_range:.3f}")
        reasons.append(f"'no return' is reported as {no_return:.4g} m: readings there are not walls")
    if max_range == tb.max_range:
        return AutoRelocalization(options, (), ())
    tb = dataclasses.replace(tb, max_range=max_range)
    return AutoRelocalization(dataclasses.replace(options, trajectory_builder_2d=tb), tuple(settings), tuple(reasons))


def score_level(loaded) -> float | None:
    """Median score of the map's own scans where they were inserted: each sampled node's points at its local pose
    in every submap holding it (None: fewer than ``MIN_LEVEL_NODES`` nodes with points)."""
    of_node: dict[int, list[int]] = {}
    for s, nodes in enumerate(loaded.submap_nodes):
        for n in np.asarray(nodes, dtype=np.int64):
            of_node.setdefault(int(n), []).append(s)
    usable = [n for n in sorted(of_node) if n < len(loaded.node_points) and len(loaded.node_points[n])]
    if len(usable) < MIN_LEVEL_NODES:
        return None
    picked = [usable[i] for i in np.unique(np.linspace(0, len(usable) - 1, LEVEL_NODES).astype(np.int64))]
    scores: list[float] = []
    for n in picked:
        # A grid lives in its trajectory's local frame, where the node's scan was inserted: its local pose. (At the
        # global pose instead, the optimisation's compromise between a node and its submaps reads as a blurred
        # map: the tests' simulated map 0.60 against 0.77, its right answers scoring 0.82.)
        pose = np.asarray(loaded.node_local_poses[n], dtype=np.float64)
        points = np.asarray(loaded.node_points[n], dtype=np.float64)
        scores.extend(score_at(loaded.submaps[s].grid, points, pose) for s in of_node[n])
    return float(np.median(scores))


def choose_for_map(options: Options, loaded) -> AutoRelocalization:
    """``options`` with the score thresholds scaled to the map's :func:`score_level` (module doc)."""
    level = score_level(loaded)
    if level is None or level >= REFERENCE_LEVEL:
        return AutoRelocalization(options, (), ())
    ro = options.relocalization
    k = level / REFERENCE_LEVEL
    scaled = {name: round(getattr(ro, name) * k, 3)
              for name in ("min_score", "global_min_score", "global_search_min_score")}
    reason = (f"the map's own scans score {level:.3f} in it (median), below the {REFERENCE_LEVEL:g} of the maps the "
              f"thresholds were set on: thresholds x {k:.2f}")
    ro = dataclasses.replace(ro, **scaled)
    return AutoRelocalization(dataclasses.replace(options, relocalization=ro),
                              tuple(f"relocalization.{name}={v:g}" for name, v in scaled.items()),
                              (reason,) * len(scaled))
