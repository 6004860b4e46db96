"""How well relocalization works on a recording: the one harness behind the tuning objective, `carto profile
--relocalize` and bench/relocalization.py.

A caller picks scans (``scans_by_index``, ``every_nth_scan``), makes each a :class:`Probe` (the prior it is
given, and the reference pose a right answer lies near, in the map frame), and :func:`run_probes` relocalizes
them in order; an :class:`Outcome` is correct when the answer is within the caller's tolerance of the reference
(:func:`pose_error`), a success when the relocalizer also claimed it. :func:`summarize_outcomes` counts successes,
claims and false matches and gives the latency percentiles. How the priors and references are made (perturbation,
alignment of a ground truth to the map) stays with the caller: that is what differs between them.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Scan
from carto_cli.io.topics import select_topics, selected_records
from carto_cli.relocalization import (
    Latency,
    Query,
    RelocalizationResult,
    Relocalizer,
    ScanContext,
    contexts_for,
    scans_for_queries,
)
from carto_cli.relocalization.queries import CONTEXT_SECONDS

__all__ = ["Outcome", "Probe", "Summary", "every_nth_scan", "pose_error", "run_probes", "scans_by_index",
           "scans_with_context", "summarize_outcomes", "within"]


@dataclass(frozen=True)
class Probe:
    """One evaluation query: a scan, its prior (None: a global search) and where a right answer lies."""

    scan_index: int
    scan: Scan
    prior: object = None  # (x, y, yaw) in the map frame
    reference: object = None  # (x, y, yaw) in the map frame; None: the relocalizer's own verdict is taken
    sigma_xy: float | None = None  # None: the relocalizer's default
    sigma_yaw: float | None = None
    context: ScanContext | None = None  # the recording around the scan, as `carto relocalize` passes it


@dataclass
class Outcome:
    """A probe's answer and how it compares with the reference."""

    probe: Probe
    result: RelocalizationResult | None  # None: the relocalizer refused the query (``refusal`` says why)
    refusal: str = ""
    error_xy: float | None = None  # m, answer to reference (None without either)
    error_yaw: float | None = None  # rad, absolute
    correct: bool | None = None  # within the tolerance of the reference; None without either

    @property
    def claimed(self) -> bool:
        """The relocalizer reported success."""
        return self.result is not None and bool(self.result.success)

    @property
    def ok(self) -> bool:
        """Claimed, and right when there is a reference to judge by."""
        return self.claimed and self.correct is not False

    @property
    def ms(self) -> float | None:
        return None if self.result is None else self.result.total_ms


@dataclass(frozen=True)
class Summary:
    queries: int
    successes: int  # Outcome.ok
    claimed: int
    false_matches: int  # claimed but not correct
    refused: int
    latency: Latency  # over the answered queries
    paths: dict[str, int] = field(default_factory=dict)  # answered queries by search path, in order of appearance

    @property
    def success_rate(self) -> float:
        return self.successes / self.queries if self.queries else 0.0


def pose_error(reference, pose) -> tuple[float, float]:
    """(distance in m, absolute heading difference in rad) of ``pose`` from ``reference``."""
    d = transform.relative(reference, pose)
    return math.hypot(d[0], d[1]), abs(float(transform.wrap_angle(d[2])))


def within(reference, pose, tolerance: tuple[float, float]) -> bool:
    """Whether ``pose`` is within ``tolerance`` (m, rad) of ``reference``."""
    exy, eyaw = pose_error(reference, pose)
    return exy <= tolerance[0] and eyaw <= tolerance[1]


def scans_by_index(recording, indices: Sequence[int], scan_topic: str | None = None) -> list[tuple[int, Scan]]:
    """(index, scan) for each of ``indices`` (counted over the scan topic from 0), in their order, in one pass."""
    found = scans_for_queries(recording, [Query(None, int(i), None) for i in indices], scan_topic)
    return [found[k] for k in range(len(indices))]


def scans_with_context(recording, indices: Sequence[int], scan_topic: str | None = None, *,
                       context_seconds: float = CONTEXT_SECONDS) -> list[tuple[int, Scan, ScanContext]]:
    """``scans_by_index`` with each scan's records around it (``relocalization.contexts_for``), in one pass."""
    found, contexts = contexts_for(recording, [Query(None, int(i), None) for i in indices], scan_topic,
                                   context_seconds=context_seconds)
    return [(*found[k], contexts.get(k, ScanContext())) for k in range(len(indices))]


def every_nth_scan(recording, every: int, scan_topic: str | Sequence[str] | None = None
                   ) -> Iterator[tuple[int, Scan]]:
    """(index, scan) of scans 0, every, 2 every, ... as the recording is read (several lasers' merged, as mapping
    reads them)."""
    selection = select_topics(recording, scan_topic)
    scans = (r for r in selected_records(recording, selection, list(selection.scan_topics)) if isinstance(r, Scan))
    for i, scan in enumerate(scans):
        if i % every == 0:
            yield i, scan


def run_probes(relocalizer: Relocalizer, probes: Iterable[Probe], *, tolerance: tuple[float, float] | None = None,
               max_queries: int | None = None, record_refusals: bool = False) -> list[Outcome]:
    """Relocalize every probe in order (at most ``max_queries``; ``probes`` is read no further) and judge it.

    ``tolerance`` (m, rad) judges answers against the probes' references. With ``record_refusals`` a query the
    relocalizer refuses (CartoError: a prior far from the map, a scan without returns) is an outcome without a
    result instead of an error.
    """
    out: list[Outcome] = []
    for probe in probes:
        try:
            r = relocalizer.relocalize(probe.scan, probe.prior, sigma_xy=probe.sigma_xy, sigma_yaw=probe.sigma_yaw,
                                       context=probe.context)
        except CartoError as e:
            if not record_refusals:
                raise
            out.append(Outcome(probe, None, refusal=str(e)))
        else:
            outcome = Outcome(probe, r)
            if probe.reference is not None:
                if tolerance is None:
                    raise ValueError("probes with a reference need a tolerance to be judged by")
                outcome.error_xy, outcome.error_yaw = pose_error(probe.reference, r.pose)
                outcome.correct = outcome.error_xy <= tolerance[0] and outcome.error_yaw <= tolerance[1]
            out.append(outcome)
        if max_queries is not None and len(out) >= max_queries:
            break
    return out


def summarize_outcomes(outcomes: Sequence[Outcome]) -> Summary:
    answered = [o for o in outcomes if o.result is not None]
    paths: dict[str, int] = {}
    for o in answered:
        assert o.result is not None
        paths[o.result.path] = paths.get(o.result.path, 0) + 1
    return Summary(
        queries=len(outcomes),
        successes=sum(o.ok for o in outcomes),
        claimed=sum(o.claimed for o in outcomes),
        false_matches=sum(o.claimed and o.correct is False for o in outcomes),
        refused=len(outcomes) - len(answered),
        latency=Latency.of([o.ms for o in answered]),
        paths=paths,
    )
