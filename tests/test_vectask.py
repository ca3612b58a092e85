"""VecTask: E worlds stepped as arrays give, world by world, what a lone TaskEnv with
the same seed gives: observations, rewards, success, collisions and ends bit for bit
(float64 physics in mpe2's order, the same float32 cast), over many random episodes per
task and per task option, resets and success-terminal new worlds included."""

from __future__ import annotations

import numpy as np
import pytest

from shared.envs.tasks import make_task
from shared.envs.vectask import ListTask, VecTask, vectorize

CASES = [
    ("simple", {}),
    ("simple", {"reward": "dense"}),
    ("simple", {"reward": "sparse_offset", "success_terminal": True, "landmark_size": 0.4}),
    ("simple", {"integrator": "velocity-first", "pad_obs": True}),
    ("spread", {"agents": 2}),
    ("spread", {"agents": 3, "reward": "dense"}),
    ("spread", {"agents": 2, "cover": "landmark", "comm_obs": False, "pad_obs": True}),
    ("spread", {"agents": 3, "success_terminal": True, "landmark_size": 0.6,
                "integrator": "velocity-first"}),
    ("speaker_listener", {}),
    ("speaker_listener", {"reward": "dense"}),
    ("speaker_listener", {"pad_obs": True, "success_terminal": True, "landmark_size": 0.5,
                          "integrator": "velocity-first", "cover": "landmark"}),
]  # fmt: skip


def _pair(task: str, opts: dict, worlds: int, seed0: int = 100):
    lone = [make_task(task, seed=seed0 + i, **opts) for i in range(worlds)]
    vec = VecTask([make_task(task, **opts) for _ in range(worlds)])
    return lone, vec


def run_side_by_side(task: str, opts: dict, worlds: int = 6, episodes: int = 8, cross=None):
    """Step both for `episodes` episodes of random actions (some outside the box, to
    clip); return how many terminal successes were seen. `cross` swaps two worlds'
    RNG streams in the VecTask (the check that the test can fail)."""
    lone, vec = _pair(task, opts, worlds)
    rng = np.random.default_rng(7)
    spec = vec.spec
    seeds = [100 + i for i in range(worlds)]
    if cross:
        seeds[cross[0]], seeds[cross[1]] = seeds[cross[1]], seeds[cross[0]]
    terminal = 0
    for ep in range(episodes):
        ref = [np.concatenate(e.reset()) for e in lone]
        got = [vec.reset(i, seed=seeds[i] if ep == 0 else None) for i in range(worlds)]
        np.testing.assert_array_equal(np.stack(got), np.stack(ref))
        for _ in range(spec.episode_len):
            acts = rng.uniform(-1.3, 1.3, (worlds, spec.joint_act_dim)).astype(np.float32)
            res = vec.step(acts)
            for i, env in enumerate(lone):
                r = env.step_joint(acts[i])
                assert np.array_equal(res.obs[i], r.obs), (i, res.obs[i], r.obs)
                assert res.reward[i] == r.reward, (i, res.reward[i], r.reward)
                assert res.success[i] == r.success
                assert res.collisions[i] == r.collisions
                assert res.truncated[i] == r.truncated
                assert res.terminated[i] == r.terminated
                if r.terminated and not r.truncated:
                    terminal += 1
                    np.testing.assert_array_equal(
                        vec.reset_world(i), np.concatenate(env.reset_world())
                    )
            if res.truncated.all():
                break
    return terminal


@pytest.mark.parametrize("task,opts", CASES, ids=[f"{t}-{i}" for i, (t, _) in enumerate(CASES)])
def test_vectask_equals_lone_worlds(task, opts):
    terminal = run_side_by_side(task, opts)
    if opts.get("success_terminal"):
        assert terminal > 0, "no terminal success happened: the reset_world path went untested"


def test_collisions_happen_and_match():
    """Crowded spread worlds (big agents): contact forces and collision counts matter."""
    lone, vec = _pair("spread", {"agents": 4, "landmark_size": 0.3}, 4)
    for e in lone:
        for a in e.world.agents:
            a.size = 0.4
    for i in range(4):
        vec.reset(i, seed=100 + i)
        lone[i].reset()
        for a in lone[i].world.agents:
            a.size = 0.4
    vec.size[:, :4] = 0.4
    seen = 0
    rng = np.random.default_rng(1)
    for _ in range(20):
        acts = rng.uniform(-1, 1, (4, vec.spec.joint_act_dim)).astype(np.float32)
        res = vec.step(acts)
        for i, env in enumerate(lone):
            r = env.step_joint(acts[i])
            assert np.array_equal(res.obs[i], r.obs)
            assert res.reward[i] == r.reward and res.collisions[i] == r.collisions
            seen += r.collisions
    assert seen > 0


def test_crossed_rng_streams_fail():
    """Two worlds' seeds swapped: the comparison must notice."""
    with pytest.raises(AssertionError):
        run_side_by_side("speaker_listener", {}, worlds=3, episodes=1, cross=(0, 1))


def test_rng_state_round_trip():
    lone, vec = _pair("simple", {}, 2)
    vec.reset(0, seed=5)
    vec.reset(1, seed=6)
    state = vec.rng_state(1)
    first = vec.reset(1)
    vec.set_rng_state(1, state)
    np.testing.assert_array_equal(vec.reset(1), first)


def test_refuses_bad_use():
    vec = VecTask([make_task("simple") for _ in range(2)])
    with pytest.raises(RuntimeError, match="reset"):
        vec.step(np.zeros((2, 2), np.float32))
    vec.reset(0, seed=1)
    vec.reset(1, seed=2)
    with pytest.raises(ValueError, match="shape"):
        vec.step(np.zeros((3, 2), np.float32))
    with pytest.raises(ValueError, match="non-finite actions in worlds \\[1\\]"):
        vec.step(np.array([[0, 0], [np.nan, 0]], np.float32))
    with pytest.raises(ValueError, match="same task"):
        VecTask([make_task("simple"), make_task("simple", integrator="velocity-first")])


def test_rewards_may_differ_per_world():
    """A group's sparse, offset and dense arms share one VecTask: each world is scored
    with its own reward, as its lone env scores it."""
    kinds = ["sparse", "dense", "sparse_offset", "dense"]
    lone = [make_task("speaker_listener", reward=k, seed=i) for i, k in enumerate(kinds)]
    vec = VecTask([make_task("speaker_listener", reward=k) for k in kinds])
    for i, e in enumerate(lone):
        e.reset()
        vec.reset(i, seed=i)
    rng = np.random.default_rng(3)
    for _ in range(20):
        acts = rng.uniform(-1, 1, (4, vec.spec.joint_act_dim)).astype(np.float32)
        res = vec.step(acts)
        assert [e.step_joint(a).reward for e, a in zip(lone, acts)] == res.reward.tolist()


def test_custom_tasks_step_world_by_world():
    envs = [make_task("tests.custom_envs:tiny", episode_len=5) for _ in range(2)]
    vt = vectorize(envs)
    assert isinstance(vt, ListTask)
    for i in range(2):
        vt.reset(i, seed=i)
    res = vt.step(np.zeros((2, vt.spec.joint_act_dim), np.float32))
    assert res.obs.shape == (2, vt.spec.joint_obs_dim)
