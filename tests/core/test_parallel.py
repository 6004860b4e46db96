"""core.parallel: results in input order whatever the number of threads."""
import threading
import time

from carto_cli.core.parallel import available_cores, map_ordered


def test_results_come_back_in_input_order_from_several_threads():
    seen = set()

    def slow_square(x):
        seen.add(threading.get_ident())
        time.sleep(0.002 * (7 - x % 7))  # later items finish first
        return x * x

    assert map_ordered(slow_square, range(20), jobs=3) == [x * x for x in range(20)]
    assert len(seen) > 1
    assert map_ordered(slow_square, range(20), jobs=1) == [x * x for x in range(20)]
    assert map_ordered(slow_square, [], jobs=4) == []


def test_available_cores_is_at_least_one():
    assert available_cores() >= 1
