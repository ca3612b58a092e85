import numpy as np
import pytest

from shared.core.replay import ReplayBuffer


@pytest.mark.parametrize("n", [0, 5, 10, 23])
def test_len_is_min_of_capacity_and_added(n):
    buf = ReplayBuffer(10, 3, 2)
    for i in range(n):
        buf.add(np.full(3, i), np.full(2, i), float(i), np.full(3, i + 1), 0.0)
    assert len(buf) == min(10, n) and buf.added == n


def test_ring_overwrites_oldest_and_batches_match_rows():
    buf = ReplayBuffer(4, 1, 1)
    obs = np.arange(6, dtype=np.float32)[:, None]
    buf.add(obs, obs, np.arange(6), obs + 1, np.zeros(6))
    assert sorted(buf.obs[:, 0].tolist()) == [2, 3, 4, 5]
    b = buf.sample(50, np.random.default_rng(0))
    assert np.array_equal(b.obs[:, 0], b.rew)
    assert np.array_equal(b.next_obs, b.obs + 1)
    assert set(b.obs[:, 0].tolist()) <= {2, 3, 4, 5}


def test_sampling_does_not_change_the_buffer():
    buf = ReplayBuffer(100, 2, 2)
    rng = np.random.default_rng(1)
    buf.add(rng.random((60, 2)), rng.random((60, 2)), rng.random(60), rng.random((60, 2)), 0.0)
    snapshot = buf.obs.copy(), buf.rew.copy()
    for _ in range(100):
        buf.sample(32, rng)
    assert np.array_equal(snapshot[0], buf.obs) and np.array_equal(snapshot[1], buf.rew)


def test_empty_buffer_refuses_to_sample():
    with pytest.raises(ValueError):
        ReplayBuffer(3, 1, 1).sample(1, np.random.default_rng(0))
