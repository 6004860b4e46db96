"""Relocalization: a scan's pose in a saved map, from a prior pose or from nothing.

``relocalizer`` holds the search (an ordered list of stages), ``following`` the staged policy for a scan that
follows a known pose, ``tracking`` a whole recording followed through the map, ``auto`` the search settings
chosen from the map, ``queries`` the query files, scan selection and the records around a query scan, ``result``
what a query, a batch or one judgement answers. ``following`` needs of a relocalizer only what its ``MapToFollow``
names, so the modules import one another one way (each imported by those after it): queries, result, following,
relocalizer, tracking.
The LRU of precomputation stacks is ``carto_cli.matching.stack_cache.StackCache``.
"""
from carto_cli.matching.stack_cache import StackCache
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
from carto_cli.relocalization.relocalizer import Candidate, Relocalizer, relocalize_many
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
