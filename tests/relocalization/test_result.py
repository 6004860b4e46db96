"""What a relocalization answers: a result's JSON, the timing buckets, a batch's summary and CSV."""
import time

import numpy as np
import pytest

from carto_cli.relocalization import (
    CSV_COLUMNS,
    PATHS,
    TIMING_BUCKETS,
    Latency,
    Query,
    QueryResult,
    RelocalizationResult,
    Timings,
    summarize,
    write_results_csv,
)


def _result(path="windowed", success=True, total_ms=4.0, submap=2, pose=(1.0, 2.0, 0.5)):
    timings = {"submap preparation": 1.0, "pose search": 2.0, "scan scoring": 0.5, "other": total_ms - 3.5}
    return RelocalizationResult(np.array(pose), 0.71234567, path, success, [2, 3], timings, total_ms, submap,
                                0.65, "" if success else "refined score 0.4 below 0.55", 0.55)


def _row(k, **kw):
    return QueryResult(Query(1000.0 + k, None, None, line=k + 1), 10 * k, 1000.0 + k, _result(**kw))


def test_result_to_dict_is_json_ready():
    d = _result().to_dict()
    assert d["pose"] == {"x": 1.0, "y": 2.0, "yaw": 0.5}
    assert d["score"] == 0.712346 and d["search_score"] == 0.65 and d["threshold"] == 0.55
    assert d["path"] == "windowed" and d["success"] is True and d["submap"] == 2
    assert d["submaps_considered"] == [2, 3] and list(d["timings_ms"]) == list(TIMING_BUCKETS)
    assert d["total_ms"] == 4.0


def test_timings_leave_the_rest_to_other():
    tm = Timings()
    t = time.perf_counter()
    time.sleep(0.002)
    tm.add("pose search", t)
    time.sleep(0.002)
    ms, total = tm.finish()
    assert list(ms) == list(TIMING_BUCKETS)
    assert ms["pose search"] >= 2.0 and ms["other"] >= 2.0 and ms["scan scoring"] == 0.0
    assert sum(ms.values()) == pytest.approx(total)


def test_latency_of_values_and_of_none():
    lat = Latency.of([4.0, 1.0, 3.0, 2.0])
    assert lat.mean_ms == 2.5 and lat.p50_ms == 2.5 and lat.max_ms == 4.0
    assert lat.p95_ms == pytest.approx(3.85) and lat.p95_ms <= lat.p99_ms <= lat.max_ms
    assert Latency.of([]) == Latency(None, None, None, None, None)


def test_summarize_counts_paths_and_percentiles():
    rows = [_row(0, total_ms=4.0), _row(1, total_ms=8.0, path="global"), _row(2, success=False, total_ms=6.0)]
    s = summarize(rows)
    assert s.queries == 3 and s.successes == 2 and s.success_rate == pytest.approx(2 / 3)
    assert (s.p50_ms, s.max_ms) == (6.0, 8.0) and s.p50_ms <= s.p95_ms <= s.p99_ms <= s.max_ms
    assert list(s.paths) == list(PATHS) and s.paths["windowed"] == 2 and s.paths["global"] == 1
    assert s.timings_ms["pose search"] == 2.0 and s.timings_ms["other"] == pytest.approx(2.5)
    assert s.verdicts == {"ok": 2, "ambiguous": 0, "lost": 1}
    d = s.to_dict()
    assert d["success_rate"] == 0.667 and d["paths"]["fallback-all"] == 0
    empty = summarize([])
    assert (empty.queries, empty.success_rate, empty.p99_ms, empty.max_ms) == (0, 0.0, 0.0, 0.0)


def test_results_csv_is_written_atomically(tmp_path):
    rows = [_row(0), _row(1, success=False, submap=None, path="fallback-all")]
    out = write_results_csv(tmp_path / "out" / "results.csv", rows)
    lines = out.read_text().splitlines()
    assert lines[0].split(",") == list(CSV_COLUMNS) and len(lines) == 3
    assert lines[1] == "1000.000000,0,1.0000,2.0000,0.50000,ok,0.7123,0.0000,0.0000,0,0,,,,,,,windowed,4.00,1,2,"
    assert lines[2].endswith(",fallback-all,4.00,0,,refined score 0.4 below 0.55")
    assert ",lost," in lines[2]
    assert not [f for f in out.parent.iterdir() if f.name.startswith(".")]  # no temporary left behind
