"""Relocalization: a scan's pose in a saved map, from a prior pose or from nothing.

``relocalizer`` holds the face of a query's way (``Relocalizer``), over objects with one job each: ``map_index``
the map side (grids, frames, boxes, covering set, distance filters, scan preprocessing), ``judge`` the fit,
refinement, covariance, ambiguity and verdict of a pose, ``search`` the windowed and whole-submap searches,
``stages`` the staged policy (which search when, a frozen query and what a stage hands the next); ``batch`` runs a
file of queries. ``following`` follows a scan from a known pose (judged by the judge), ``tracking`` a whole
recording through the map, ``auto`` the search settings chosen from the map, ``queries`` the query files, scan
selection and the records around a query scan, ``result`` what a query, a batch or one judgement answers. The
modules import one another one way (each imported by those after it): queries, result, map_index, judge,
following and search, stages, relocalizer, batch and tracking.
The LRU of precomputation stacks is ``carto_cli.matching.stack_cache.StackCache``.
"""
from carto_cli.matching.stack_cache import StackCache
from carto_cli.relocalization.batch import relocalize_many
from carto_cli.relocalization.queries import (
    Query,
    ScanContext,
    context_at,
    contexts_for,
    iter_scans,
    parse_pose,
    read_queries,
    scan_at,
    scans_for_queries,
    select_scan_topic,
)
from carto_cli.relocalization.relocalizer import Candidate, Relocalizer
from carto_cli.relocalization.result import (
    CSV_COLUMNS,
    PATHS,
    TIMING_BUCKETS,
    VERDICTS,
    BatchSummary,
    Latency,
    PoseVerdict,
    QueryResult,
    RelocalizationResult,
    SearchPath,
    Timings,
    summarize,
    write_results_csv,
)

__all__ = [
    "CSV_COLUMNS", "PATHS", "TIMING_BUCKETS", "VERDICTS", "BatchSummary", "Candidate", "Latency", "PoseVerdict",
    "Query", "QueryResult", "RelocalizationResult", "Relocalizer", "ScanContext", "SearchPath", "StackCache",
    "Timings", "context_at",
    "contexts_for", "iter_scans", "parse_pose",
    "read_queries", "relocalize_many", "scan_at", "scans_for_queries", "select_scan_topic", "summarize",
    "write_results_csv",
]
