"""``carto relocalize`` with no profile: settings chosen from the map and the scans, as ``carto map`` chooses its own.

A map.carto carries the options it was built with (chosen by ``--profile auto`` when it was mapped): the scans
are filtered as they were then. A map_server image carries none, so the scans decide what the defaults cannot
know: a laser that reports "no return" as a fixed reading at the top of its range (the dense benchmarks' 30 m,
a Hokuyo's 5.6 m) would put phantom points on a circle at that range, so the range is cut just below it, as
mapping does (``regime.no_return_value``); a sensor that reaches less than the default range keeps its own limit.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from carto_cli.core.records import Scan
from carto_cli.options import Options
from carto_cli.regime import no_return_value

__all__ = ["AutoRelocalization", "choose_for_scans"]


@dataclasses.dataclass(frozen=True)
class AutoRelocalization:
    options: Options
    settings: tuple[str, ...]  # 'key=value' of what was changed
    reasons: tuple[str, ...]

    def describe(self) -> str:
        if not self.settings:
            return "defaults (nothing in the scans calls for other settings)"
        return "; ".join(f"{s} ({r})" for s, r in zip(self.settings, self.reasons))


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
