"""`carto relocalize` as a library call: load the map, build the relocalizer, answer one scan or a queries file."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from carto_cli.core.errors import CartoError
from carto_cli.core.progress import progress
from carto_cli.core.records import Scan
from carto_cli.io.map_file import load_map
from carto_cli.io.recording import ReadOptions
from carto_cli.io.sources.open import open_recording
from carto_cli.options import apply_overrides
from carto_cli.relocalization import (
    BatchSummary,
    QueryResult,
    RelocalizationResult,
    Relocalizer,
    parse_pose,
    read_queries,
    relocalize_many,
    scan_at,
    write_results_csv,
)

__all__ = ["RelocalizeRun", "run_relocalize"]


@dataclass
class RelocalizeRun:
    """What `carto relocalize` answered: one scan (``result``) or a batch (``results``, ``summary``, ``csv``)."""

    warnings: list[str] = field(default_factory=list)
    scan_index: int | None = None
    scan: Scan | None = None
    result: RelocalizationResult | None = None
    results: list[QueryResult] | None = None
    summary: BatchSummary | None = None
    csv: Path | None = None

    @property
    def batch(self) -> bool:
        return self.summary is not None

    def to_dict(self) -> dict:
        """JSON-ready: the batch summary, or the one result with its scan's index and time."""
        if self.summary is not None:
            return self.summary.to_dict()
        assert self.result is not None and self.scan is not None
        data = self.result.to_dict()
        data["scan_index"] = self.scan_index
        data["scan_time"] = self.scan.time
        return data


def run_relocalize(
    map_file: Path,
    recording: Path,
    *,
    initial_pose: str | Sequence[float] | None = None,
    at: float | None = None,
    scan_index: int | None = None,
    sigma_xy: float | None = None,
    sigma_yaw: float | None = None,
    corridor: bool = False,
    global_search: bool = False,
    queries: Path | None = None,
    csv_out: Path | None = None,
    scan_topic: str | None = None,
    overrides: Sequence[str] | None = None,
    on_warning: Callable[[str], None] | None = None,
    quiet: bool = True,
    force: bool = False,
    read: ReadOptions | None = None,
) -> RelocalizeRun:
    """Relocalize one scan (``at`` / ``scan_index``, default the first) from ``initial_pose`` ('x,y,yaw' text or
    a pose) or globally, or every line of ``queries`` (results to ``csv_out``, default QUERIES.results.csv).

    ``sigma_yaw`` is in radians; ``overrides`` are ``--set`` items over the map's own options. The relocalizer's
    warnings go to ``on_warning`` as soon as it is built (before the recording is read), and into the result.
    ``quiet=False`` shows a progress bar over a batch (on a terminal). An existing results CSV is replaced only
    with ``force`` (refused before any work). ``read``: how point clouds are sliced (io.recording.ReadOptions).
    """
    if queries is None and not global_search and initial_pose is None:
        raise CartoError("give --initial-pose x,y,yaw, or --global, or --queries FILE")
    if global_search and initial_pose is not None:
        raise CartoError("--global and --initial-pose exclude each other")
    if at is not None and scan_index is not None:
        raise CartoError("--at and --scan-index exclude each other")
    if queries is not None:
        csv_out = csv_out or queries.with_suffix(".results.csv")
        if csv_out.exists() and not force:
            raise CartoError("exists; --force replaces it, or give another --csv", csv_out)

    loaded = load_map(map_file)
    relocalizer = Relocalizer(loaded, apply_overrides(loaded.options, overrides) if overrides else None)
    run = RelocalizeRun(warnings=list(relocalizer.warnings))
    if on_warning is not None:
        for w in relocalizer.warnings:
            on_warning(w)
    with open_recording(recording, read) as rec:
        if queries is not None:
            qs = read_queries(queries)
            with progress("relocalizing", len(qs), quiet) as bar:
                run.results, run.summary = relocalize_many(relocalizer, rec, qs, scan_topic=scan_topic,
                                                           corridor=corridor, on_query=bar.advance)
            assert csv_out is not None
            run.csv = write_results_csv(csv_out, run.results)
            return run
        run.scan_index, run.scan = scan_at(rec, time=at, index=scan_index, scan_topic=scan_topic)
    # Parsed only now, as the command always has: a bad --initial-pose is reported after the map and the scan.
    prior = None if global_search else (parse_pose(initial_pose) if isinstance(initial_pose, str) else initial_pose)
    run.result = relocalizer.relocalize(run.scan, prior, sigma_xy=sigma_xy, sigma_yaw=sigma_yaw, corridor=corridor)
    return run
