"""shared.lanes: blocks cover the rows exactly once; map returns results in order."""

import threading

import pytest

from shared.lanes import Lanes


@pytest.mark.parametrize(("n", "rows"), [(1, 100), (2, 100), (2, 7), (3, 7), (4, 2), (2, 1)])
def test_blocks_partition_the_rows(n, rows):
    blocks = Lanes(n).blocks(rows)
    covered = [i for b in blocks for i in range(rows)[b]]
    assert covered == list(range(rows))
    assert len(blocks) == min(n, rows)
    sizes = [b.stop - b.start for b in blocks]
    assert max(sizes) - min(sizes) <= 1


def test_map_runs_items_at_the_same_time_and_keeps_order():
    lanes = Lanes(3)
    seen: list[str] = []
    together = threading.Barrier(3, timeout=10)  # breaks unless all three run at once

    def f(x: int) -> int:
        seen.append(threading.current_thread().name)
        together.wait()
        return x * x

    assert lanes.map(f, [1, 2, 3]) == [1, 4, 9]
    assert seen.count(threading.current_thread().name) == 1  # first item here, the rest away
    assert len(set(seen)) == 3
    lanes.close()
    assert lanes.map(lambda x: x * x, [4, 5]) == [16, 25]  # closed: runs inline


def test_errors_in_a_lane_reach_the_caller():
    lanes = Lanes(2)
    with pytest.raises(ZeroDivisionError):
        lanes.map(lambda x: 1 / x, [1, 0])
    lanes.close()


def test_refuses_zero_lanes():
    with pytest.raises(ValueError, match="lanes"):
        Lanes(0)
