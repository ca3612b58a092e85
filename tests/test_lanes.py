"""shared.core.learners.lanes: blocks cover the rows exactly once; map returns results in order."""

import threading

import pytest

from shared.core.learners.lanes import Lanes, LaneTuner


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


def run(tuner: LaneTuner, cost: dict, updates: int) -> list:
    picks = []
    for _ in range(updates):
        k = tuner.choose()
        picks.append(k)
        tuner.record(cost[k])
    return picks


def test_tuner_tries_each_then_keeps_the_faster_with_rare_probes():
    tuner = LaneTuner((1, 2), block=10, probe_every=10)
    picks = run(tuner, {1: 0.008, 2: 0.005}, 2000)
    assert picks[:10] == [1] * 10 and picks[10:20] == [2] * 10  # each tried once
    assert tuner.best() == 2
    slow_share = picks[20:].count(1) / len(picks[20:])
    assert 0 < slow_share <= 0.1  # probes only: one block in about eleven


def test_tuner_follows_a_change_in_load():
    tuner = LaneTuner((1, 2), block=10, probe_every=5)
    run(tuner, {1: 0.008, 2: 0.005}, 500)
    assert tuner.best() == 2
    picks = run(tuner, {1: 0.008, 2: 0.016}, 500)  # the second core got busy
    assert tuner.best() == 1
    assert picks[-100:].count(1) >= 80
    # and free again: noticed at the next probe, which comes later after lost probes
    run(tuner, {1: 0.008, 2: 0.005}, 10 * tuner.block * tuner.probe_every * tuner.backoff[2])
    assert tuner.best() == 2


def test_tuner_with_one_option_never_switches():
    tuner = LaneTuner((1,), block=3)
    assert set(run(tuner, {1: 0.01}, 50)) == {1}
    with pytest.raises(ValueError):
        LaneTuner(())


def test_tuner_picks_among_three_modes():
    modes = [(1, 1), (2, 1), (1, 2)]
    tuner = LaneTuner(modes, block=5, probe_every=10)
    run(tuner, {(1, 1): 0.008, (2, 1): 0.007, (1, 2): 0.0055}, 600)
    assert tuner.best() == (1, 2)
    run(tuner, {(1, 1): 0.008, (2, 1): 0.010, (1, 2): 0.016}, 600)  # the other core busy
    assert tuner.best() == (1, 1)
    assert all(tuner.chosen[m] > 0 for m in modes)


def test_a_ruinous_mode_costs_a_single_update_now_and_then():
    """OpenMP threads under a busy core: 30x slower. Probes are cut at the first slow
    update and come ever more rarely: the total cost stays within a few percent."""
    modes = [(1, 1), (2, 1), (1, 2)]
    cost = {(1, 1): 0.008, (2, 1): 0.0095, (1, 2): 0.25}
    tuner = LaneTuner(modes, block=20, probe_every=10)
    picks = run(tuner, cost, 20_000)
    assert tuner.best() == (1, 1)
    total = sum(cost[m] for m in picks)
    assert total <= 1.05 * 20_000 * cost[(1, 1)] + 0.25 * 3  # + the first tries
    assert tuner.aborted > 0 and tuner.backoff[(1, 2)] == tuner.max_backoff
    assert picks.count((1, 2)) < 40  # one update per probe


def test_a_probe_that_wins_takes_over_at_once():
    tuner = LaneTuner([1, 2], block=10, probe_every=5)
    run(tuner, {1: 0.008, 2: 0.02}, 2000)
    assert tuner.best() == 1 and tuner.backoff[2] > 1
    picks = run(tuner, {1: 0.008, 2: 0.004}, 3000)  # load gone: 2 is now faster
    assert tuner.best() == 2 and tuner.backoff[2] == 1
    assert picks[-200:].count(2) >= 180


def test_stalls_at_each_episode_start_do_not_lock_out_the_faster_mode():
    """Another process's bursts stall updates whatever the mode, the two-thread one
    most. In the cluster they come at episode boundaries (the evaluator starts on the
    new weights), i.e. at the start of every 20-update tick and tuner block, so every
    probe began with a stall; with block means and a cut at the first slow update the
    two threads lost every probe and the cluster ran on one thread. The two threads
    are still faster, typically and on average: the tuner keeps them."""
    modes = [(1, 1), (2, 1), (1, 2)]
    typical = {(1, 1): 0.008, (2, 1): 0.0095, (1, 2): 0.0055}
    stall = {(1, 1): 0.019, (2, 1): 0.019, (1, 2): 0.03}

    def seconds(mode: tuple, i: int) -> float:
        return typical[mode] + (stall[mode] if i % 20 < 2 else 0.0)

    tuner = LaneTuner(modes)
    picks, total = [], 0.0
    for i in range(6000):
        mode = tuner.choose()
        picks.append(mode)
        total += seconds(mode, i)
        tuner.record(seconds(mode, i))
    assert tuner.best() == (1, 2)
    assert picks[1000:].count((1, 2)) >= 0.8 * len(picks[1000:])
    # and that is what pays: within 10% of always running the two threads
    assert total <= 1.1 * sum(seconds((1, 2), i) for i in range(6000))


def test_a_mode_slower_in_most_updates_loses_its_probes_early():
    """Twice as slow in every update (not a stall now and then): probes are cut after
    `min_probe` updates, not run to the end of their block."""
    tuner = LaneTuner([1, 2], block=20, probe_every=5)
    picks = run(tuner, {1: 0.008, 2: 0.02}, 4000)
    assert tuner.best() == 1 and tuner.aborted > 0
    probes = picks[40:].count(2)
    assert probes <= tuner.min_probe * (tuner.aborted + 1)
