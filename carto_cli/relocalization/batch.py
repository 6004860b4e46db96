"""A batch of relocalization queries: each against its scan, side by side on threads, in file order."""
from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext

from carto_cli.core.errors import CartoError
from carto_cli.core.parallel import available_cores
from carto_cli.io.topics import TopicSelection
from carto_cli.relocalization.queries import CONTEXT_SECONDS, Query, contexts_for, scans_for_queries
from carto_cli.relocalization.relocalizer import Relocalizer
from carto_cli.relocalization.result import BatchSummary, QueryResult, summarize

__all__ = ["relocalize_many"]


def relocalize_many(relocalizer: Relocalizer, recording, queries: Sequence[Query], *, scan_topic: str | None = None,
                    laser_pose=None, corridor: bool = False, max_time_offset: float = 1.0,
                    on_query=None, max_jump: float | None = None,
                    jobs: int | None = 1, selection: TopicSelection | None = None
                    ) -> tuple[list[QueryResult], BatchSummary]:
    """Run every query against its scan (nearest to its time, or at its index), in file order, on ``jobs``
    threads (None: every core). Queries are independent and the stack cache is shared and thread-safe, so the
    answers are the same for any number; each query's own timings then include waiting for a core. Each query
    gets the records around its scan as its context (``relocalize``), the odometry from ``selection`` (default:
    the recording's own)."""
    if not queries:
        raise CartoError("no queries")
    if relocalizer.ro.context_scans > 0:
        scans, contexts = contexts_for(recording, queries, scan_topic, max_time_offset,
                                       context_seconds=CONTEXT_SECONDS, selection=selection)
    else:
        scans, contexts = scans_for_queries(recording, queries, scan_topic, max_time_offset, selection=selection), {}

    def run(k: int) -> QueryResult:
        q = queries[k]
        i, scan = scans[k]
        r = relocalizer.relocalize(scan, q.prior, sigma_xy=q.sigma_xy, sigma_yaw=q.sigma_yaw, corridor=corridor,
                                   laser_pose=laser_pose, max_jump=max_jump, context=contexts.get(k))
        return QueryResult(q, i, scan.time, r)

    jobs = available_cores() if jobs is None else max(1, int(jobs))
    results = []
    inner = relocalizer.jobs
    if jobs > 1:
        relocalizer.jobs = 1  # the queries share the cores; a query's own searches then take one each
    try:
        with ThreadPoolExecutor(max_workers=jobs) if jobs > 1 else nullcontext() as pool:
            answers = pool.map(run, range(len(queries))) if pool is not None else map(run, range(len(queries)))
            for result in answers:  # in file order, as each is done
                results.append(result)
                if on_query is not None:
                    on_query(1)
    finally:
        relocalizer.jobs = inner
    return results, summarize(results)
