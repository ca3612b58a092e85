"""Collection and evaluation under the thesis profile's options, on the real mpe2 tasks:
success as a terminal step inside the 20-step window, and the random warm-up."""

from __future__ import annotations

import numpy as np
import pytest

from shared.config import make_config
from shared.envs.tasks import make_task, make_task_for
from shared.run.rollout import Collector, evaluate, make_collector, warmup_share


def place(entity, x: float, y: float) -> None:
    entity.state.p_pos = np.array([x, y], dtype=np.float64)
    entity.state.p_vel = np.zeros(2)


def still(obs: np.ndarray) -> np.ndarray:
    return np.zeros((len(obs), 2), np.float32)


@pytest.mark.parametrize("terminal", [False, True])
def test_a_success_is_done_with_its_terminal_obs_and_the_next_row_starts_a_new_world(terminal):
    """Row T12/T14: done=1 at the success, next_obs before the reset, the next row from
    the reset world, still 20 rows per episode; without the option none of that."""
    env = make_task("simple", success_terminal=terminal)
    col = Collector(env, 0.0, seed=0, time_limit_terminal=True)
    rows = [col.step(still) for _ in range(3)]
    lm, agent = env.world.landmarks[0], env.world.agents[0]
    place(lm, 0.3, 0.3)
    place(agent, 0.3, 0.3)  # the collector's obs is stale now; only its next_obs matters
    rows.append(col.step(still))
    success = rows[-1]
    assert success.success
    np.testing.assert_array_equal(success.next_obs, np.zeros(4, np.float32))  # terminal
    after = col.step(still)
    rows.append(after)
    if terminal:
        assert success.done == 1.0 and not success.episode_end
        assert not np.array_equal(after.obs, success.next_obs)  # a new world ...
        np.testing.assert_allclose(after.obs[2:], lm.state.p_pos - agent.state.p_pos, 1e-6)
        assert not after.success  # ... with new positions (seed 0)
    else:
        assert success.done == 0.0
        np.testing.assert_array_equal(after.obs, success.next_obs)  # the same world
        assert after.success
    rows += [col.step(still) for _ in range(15)]
    assert [r.episode_end for r in rows] == [False] * 19 + [True]
    assert [r.done for r in rows[5:]] == [float(r.success and terminal) for r in rows[5:-1]] + [1.0]
    for a, b in zip(rows[4:-1], rows[5:]):  # each row starts where the last one ended
        assert np.array_equal(a.next_obs, b.obs) != (terminal and a.success)
    assert col.episodes == 1


def test_evaluation_resets_the_world_after_a_success_and_counts_the_episode_once():
    """With success_terminal, evaluation goes on in a new world after a success (the
    thesis code's env did); the episode counts as one success, 20 steps."""
    cfg = dict(task="simple", algo="ddpg", success_terminal=True, landmark_size=1.0)
    envs = [make_task_for(make_config(cfg), seed=s) for s in range(3)]
    calls = []
    for env in envs:
        orig = env.reset_world
        env.reset_world = lambda orig=orig: calls.append(1) or orig()
    res = evaluate(still, envs, 6)
    assert res.steps == 6 * 20 and res.episodes == 6
    assert res.success_rate > 0.0 and calls  # a 1.05 cover radius: some success
    # The same episodes without the option: no world reset, the same success rate.
    plain = [
        make_task_for(make_config({**cfg, "success_terminal": False}), seed=s) for s in range(3)
    ]
    again = [make_task_for(make_config(cfg), seed=s) for s in range(3)]
    a, b = evaluate(still, plain, 6), evaluate(still, again, 6)
    assert a.success_rate == b.success_rate
    assert a.eval_return != b.eval_return  # the new worlds' rewards count


def test_warmup_actions_are_uniform_in_each_box_then_the_policys():
    """Row L1: the first warmup_steps actions are uniform draws (plus the same noise and
    clipping as the policy's), the policy is not asked; from then on it is."""
    env = make_task("speaker_listener")
    col = Collector(env, 0.0, seed=0, warmup_steps=2000)
    asked = []

    def policy(obs):
        asked.append(len(col_rows))
        return np.full((len(obs), 5), 0.25, np.float32)

    col_rows: list = []
    for _ in range(2010):
        col_rows.append(col.step(policy))
    acts = np.stack([r.act for r in col_rows])
    warm, after = acts[:2000], acts[2000:]
    assert asked == list(range(2000, 2010))  # not asked during the warm-up
    np.testing.assert_array_equal(after, np.full((10, 5), 0.25, np.float32))
    low, high = np.array([0, 0, 0, -1, -1.0]), np.array([1, 1, 1, 1, 1.0])
    assert (warm >= low).all() and (warm <= high).all()
    width = high - low
    assert (np.abs(warm.mean(0) - (low + high) / 2) < 0.05 * width).all(), warm.mean(0)
    assert (np.abs(warm.std(0) - width / np.sqrt(12)) < 0.03 * width).all(), warm.std(0)
    for d in range(5):  # uniform, not bunched: every tenth of the box is hit about equally
        hist, _ = np.histogram(warm[:, d], bins=10, range=(low[d], high[d]))
        assert hist.min() > 140 and hist.max() < 260, (d, hist)


def test_warmup_actions_get_the_policys_noise():
    env = make_task("simple")
    col = Collector(env, 0.1, seed=7, warmup_steps=5)
    rng = np.random.default_rng(7)  # the collector's generator, replayed
    for _ in range(5):
        u = rng.uniform(col.low, col.high).astype(np.float32)
        noise = rng.standard_normal(2).astype(np.float32) * col.noise_scale
        expected = np.clip(u + noise, col.low, col.high)
        np.testing.assert_array_equal(col.step(still).act, expected)


@pytest.mark.parametrize(
    ("warmup", "actors", "expected"),
    [("random", 1, [100]), ("random", 2, [50, 50]), ("random", 3, [34] * 3), ("policy", 2, [0, 0])],
)
def test_make_collector_warms_up_each_actors_share(warmup, actors, expected):
    """In the cluster each of R actors warms up while its own count times R is below
    learning_starts (docs/fidelity.md row L1); macb train is the one-actor case."""
    cfg = make_config({"task": "simple", "algo": "ddpg", "warmup": warmup})
    got = [make_collector(cfg, make_task_for(cfg), r, actors).warmup_steps for r in range(actors)]
    assert got == expected
    for n in got:
        assert n * actors >= cfg.learning_starts or warmup == "policy"
        assert (n - 1) * actors < cfg.learning_starts or n == 0
    assert warmup_share(0, 4) == 0 and warmup_share(1, 4) == 1


def test_make_collector_under_the_thesis_profile_random_for_exactly_learning_starts_steps():
    cfg = make_config(
        {"task": "spread", "algo": "cen-maddpg", "profile": "thesis", "learning_starts": 45}
    )
    col = make_collector(cfg, make_task_for(cfg))
    asked = []

    def policy(obs):
        asked.append(col.steps)
        return np.zeros((len(obs), 4), np.float32)

    rows = [col.step(policy) for _ in range(60)]
    assert asked == list(range(45, 60))
    assert rows[-1].obs.shape == (20,)  # comm-free spread: 10 per agent
    assert [r.done for r in rows if r.episode_end] == [1.0] * 3  # time_limit_terminal


def test_a_collectors_noise_and_its_worlds_draw_from_one_stream_as_fidelity_l7_says():
    """docs/fidelity.md L7: the collector seeds its noise generator and its training
    worlds with one seed, so both are the same PCG64 stream (the same increment), each
    at its own position: the k-th uniform of the warm-up is the k-th draw of the worlds.
    Kept because every published run was made so; this test says where it stands."""
    env = make_task("simple")
    c = Collector(env, 0.1, seed=7)
    ours, world = c.rng.bit_generator.state["state"], env.rng_state()["state"]
    assert ours["inc"] == world["inc"]
    start = env.world.agents[0].state.p_pos  # the world's first draws: uniform(-1, 1)
    assert np.allclose(c.rng.uniform(-1, 1, 2), start)  # the noise stream's first draws
