"""Task adapters against the real mpe2 envs: shapes, action mapping, rewards, episodes, seeds."""

from __future__ import annotations

import numpy as np
import pytest
from mpe2 import simple_speaker_listener_v4, simple_spread_v3, simple_v3

from shared.envs.tasks import (
    INTEGRATORS,
    REWARDS,
    TASKS,
    StepResult,
    TaskEnv,
    make_task,
    make_task_for,
    task_spec,
    task_spec_for,
    to_mpe_action,
)

SENSITIVITY = 5.0  # mpe2's force multiplier when agent.accel is None
FAR = 10.0


def place(entity, x: float, y: float) -> None:
    entity.state.p_pos = np.array([x, y], dtype=np.float64)
    entity.state.p_vel = np.zeros(2)


def zero_actions(env: TaskEnv) -> list[np.ndarray]:
    return [np.zeros(a.act_dim, dtype=np.float32) for a in env.spec.agents]


# --- specs ------------------------------------------------------------------------------------


def test_spec_simple() -> None:
    spec = task_spec("simple")
    assert [a.name for a in spec.agents] == ["agent_0"]
    assert spec.obs_dims == (4,) and spec.act_dims == (2,)
    assert spec.agents[0].act_low == (-1.0, -1.0) and spec.agents[0].act_high == (1.0, 1.0)
    assert spec.n_agents == 1 and spec.joint_obs_dim == 4 and spec.joint_act_dim == 2
    assert spec.episode_len == 20


def test_spec_spread_two_and_three_agents() -> None:
    spec = task_spec("spread", agents=2)
    assert [a.name for a in spec.agents] == ["agent_0", "agent_1"]
    assert spec.obs_dims == (12, 12) and spec.act_dims == (2, 2)
    assert spec.joint_obs_dim == 24 and spec.joint_act_dim == 4
    spec3 = task_spec("spread", agents=3)
    assert spec3.obs_dims == (18, 18, 18)  # 4 + 2N + 2(N-1) + 2(N-1)
    assert spec3.joint_obs_dim == 54 and spec3.joint_act_dim == 6
    env = make_task("spread", agents=3, seed=0)
    obs = env.reset()
    assert [o.shape for o in obs] == [(18,)] * 3
    res = env.step(zero_actions(env))
    assert len(res.obs) == 3
    env.close()


def test_spec_speaker_listener() -> None:
    spec = task_spec("speaker_listener", episode_len=25)
    speaker, listener = spec.agents
    assert (speaker.name, listener.name) == ("speaker_0", "listener_0")
    assert spec.obs_dims == (3, 11) and spec.act_dims == (3, 2)
    assert speaker.act_low == (0.0, 0.0, 0.0) and speaker.act_high == (1.0, 1.0, 1.0)
    assert listener.act_low == (-1.0, -1.0)
    assert spec.joint_obs_dim == 14 and spec.joint_act_dim == 5
    assert spec.episode_len == 25


def test_spec_layout_text_matches_dims() -> None:
    for task in TASKS:
        for a in task_spec(task).agents:
            sizes = [int(part.split("(")[1].split(")")[0]) for part in a.obs_layout.split()]
            assert sum(sizes) == a.obs_dim, a.obs_layout
    assert task_spec("speaker_listener").agents[0].act_layout == "message(3) in [0,1]"
    assert task_spec("simple").agents[0].act_layout == "move_xy(2) in [-1,1]"


def test_env_spec_matches_task_spec_and_obs_are_float32() -> None:
    for task in TASKS:
        env = make_task(task, seed=1)
        assert env.spec == task_spec(task)
        obs = env.reset()
        assert [o.shape[0] for o in obs] == list(env.spec.obs_dims)
        assert all(o.dtype == np.float32 for o in obs)
        env.close()


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError):
        task_spec("tag")
    with pytest.raises(ValueError):
        make_task("spread", reward="shaped")
    with pytest.raises(ValueError):
        make_task("spread", agents=0)
    env = make_task("spread", seed=0)
    with pytest.raises(RuntimeError):
        env.step(zero_actions(env))  # before reset
    env.reset()
    with pytest.raises(ValueError):
        env.step([np.zeros(2)])  # one action for two agents
    with pytest.raises(ValueError):
        env.step([np.zeros(5), np.zeros(5)])  # mpe2 layout is not accepted
    env.close()


# --- action mapping ---------------------------------------------------------------------------


MOVER = task_spec("simple").agents[0]
SPEAKER = task_spec("speaker_listener").agents[0]


@pytest.mark.parametrize(
    ("xy", "expected"),
    [
        ((0.0, 0.0), (0.0, 0.0)),
        ((1.0, 0.0), (1.0, 0.0)),
        ((-0.25, 0.75), (-0.25, 0.75)),
        ((0.3, -0.6), (0.3, -0.6)),
        ((1.5, -2.0), (1.0, -1.0)),  # clipped to the bounds first
    ],
)
def test_movement_mapping_gives_force_xy(xy: tuple[float, float], expected: tuple[float, float]):
    m = to_mpe_action(MOVER, np.array(xy))
    assert m.shape == (5,) and m.dtype == np.float32
    assert m[0] == 0.0 and np.all(m >= 0.0) and np.all(m <= 1.0)
    force = np.array([m[2] - m[1], m[4] - m[3]])  # mpe2's continuous rule
    np.testing.assert_array_equal(force, np.asarray(expected, dtype=np.float32))


def test_mapping_layout_exact() -> None:
    m = to_mpe_action(MOVER, np.array([0.5, -0.25]))
    np.testing.assert_array_equal(m, np.array([0.0, 0.0, 0.5, 0.25, 0.0], np.float32))


def test_speaker_message_passes_through_and_clips() -> None:
    msg = np.array([0.1, 0.7, 0.35])
    np.testing.assert_array_equal(to_mpe_action(SPEAKER, msg), msg.astype(np.float32))
    np.testing.assert_array_equal(
        to_mpe_action(SPEAKER, np.array([1.5, -0.2, 0.5])), np.array([1.0, 0.0, 0.5], np.float32)
    )


def test_mapping_rejects_nan_and_wrong_size() -> None:
    with pytest.raises(ValueError):
        to_mpe_action(MOVER, np.array([np.nan, 0.0]))
    with pytest.raises(ValueError):
        to_mpe_action(MOVER, np.zeros(3))


def test_step_applies_force_and_moves_agent() -> None:
    env = make_task("simple", seed=3)
    env.reset()
    agent = env.world.agents[0]
    start = agent.state.p_pos.copy()
    res = env.step([np.array([0.3, -0.6])])
    np.testing.assert_allclose(agent.action.u, np.array([0.3, -0.6]) * SENSITIVITY, rtol=1e-6)
    # mpe2 integrates position before velocity: velocity = force * dt / mass = (0.15, -0.3).
    np.testing.assert_allclose(res.obs[0][:2], [0.15, -0.3], rtol=1e-5)
    mid = agent.state.p_pos.copy()
    np.testing.assert_allclose(mid, start)
    env.step([np.array([0.3, -0.6])])
    delta = agent.state.p_pos - mid
    assert delta[0] > 0 and delta[1] < 0  # +x and -y, as asked
    np.testing.assert_allclose(delta, [0.015, -0.03], rtol=1e-5)
    env.close()


def test_out_of_range_action_is_clipped_in_env() -> None:
    env = make_task("spread", seed=3)
    env.reset()
    env.step([np.array([3.0, -0.5]), np.array([-9.0, 9.0])])
    np.testing.assert_allclose(env.world.agents[0].action.u, [5.0, -2.5])
    np.testing.assert_allclose(env.world.agents[1].action.u, [-5.0, 5.0])
    env.close()


def test_speaker_message_reaches_listener() -> None:
    env = make_task("speaker_listener", seed=2)
    env.reset()
    msg = np.array([0.2, 0.9, 0.4])
    res = env.step([msg, np.zeros(2)])
    np.testing.assert_allclose(res.obs[1][-3:], msg, rtol=1e-6)
    env.close()


# --- hand-placed states: reward, success, collisions ------------------------------------------


def evaluate_all(env: TaskEnv) -> dict[str, tuple[float, bool, int]]:
    """Evaluate the same world state under every sparse reward kind."""
    out = {}
    for kind in ("sparse", "sparse_offset"):
        env.reward_kind = kind
        out[kind] = env.evaluate()
    return out


def test_simple_cover_and_miss() -> None:
    env = make_task("simple", seed=0)
    env.reset()
    agent, lm = env.world.agents[0], env.world.landmarks[0]
    assert agent.size == pytest.approx(0.05) and lm.size == pytest.approx(0.05)
    place(lm, 0.3, 0.3)
    place(agent, 0.3 + 0.09, 0.3)  # 0.09 < 0.05 + 0.05
    got = evaluate_all(env)
    assert got["sparse"] == (0.0, True, 0)
    assert got["sparse_offset"] == (pytest.approx(0.7), True, 0)
    place(agent, 0.3, 0.3 + 0.11)
    got = evaluate_all(env)
    assert got["sparse"] == (-1.0, False, 0)
    assert got["sparse_offset"] == (pytest.approx(-0.3), False, 0)
    env.close()


def test_spread_sizes_are_thesis_sizes() -> None:
    for n in (2, 3):
        env = make_task("spread", agents=n, seed=0)
        for _ in range(2):
            env.reset()
            assert all(e.size == 0.125 for e in env.world.entities)
            assert len(env.world.landmarks) == n
        env.close()


def test_spread_two_agents_all_covered() -> None:
    env = make_task("spread", agents=2, seed=0)
    env.reset()
    (a0, a1), (l0, l1) = env.world.agents, env.world.landmarks
    place(l0, 0.0, 0.0)
    place(l1, 1.0, 0.0)
    place(a0, 0.1, 0.0)
    place(a1, 1.0, 0.2)  # 0.2 < 0.25: covered only with the thesis's sizes
    got = evaluate_all(env)
    assert got["sparse"] == (0.0, True, 0)
    assert got["sparse_offset"] == (pytest.approx(0.7), True, 0)
    env.close()


def test_spread_two_agents_one_uncovered_one_collision() -> None:
    env = make_task("spread", agents=2, seed=0)
    env.reset()
    (a0, a1), (l0, l1) = env.world.agents, env.world.landmarks
    place(l0, 0.0, 0.0)
    place(l1, 1.0, 0.0)
    place(a0, 0.0, 0.0)
    place(a1, 0.2, 0.0)  # both on landmark 0 and 0.2 apart: one collision, l1 uncovered
    got = evaluate_all(env)
    assert got["sparse"] == (-1.0, False, 1)
    assert got["sparse_offset"] == (pytest.approx(-0.3), False, 1)
    # Colliding and covering need a strict '<': exactly 0.125 + 0.125 apart is neither.
    place(a1, 0.25, 0.0)  # touches a0: no collision
    assert evaluate_all(env)["sparse"] == (-0.5, False, 0)
    place(a1, 1.25, 0.0)  # touches landmark 1: not covered
    assert evaluate_all(env)["sparse"] == (-0.5, False, 0)
    env.close()


def test_spread_collision_while_all_covered_is_not_zero() -> None:
    env = make_task("spread", agents=2, seed=0)
    env.reset()
    (a0, a1), (l0, l1) = env.world.agents, env.world.landmarks
    place(l0, 0.0, 0.0)
    place(l1, 0.2, 0.0)
    place(a0, 0.0, 0.0)
    place(a1, 0.2, 0.0)
    assert evaluate_all(env)["sparse"] == (-0.5, True, 1)
    env.close()


def test_spread_three_agents() -> None:
    env = make_task("spread", agents=3, seed=0)
    env.reset()
    a, lm = env.world.agents, env.world.landmarks
    place(lm[0], 0.0, 0.0)
    place(lm[1], 1.0, 0.0)
    place(lm[2], -1.0, 0.0)
    place(a[0], 0.0, 0.0)
    place(a[1], 0.1, 0.0)  # collides with a0
    place(a[2], 1.0, 0.0)  # lm[2] is left uncovered
    got = evaluate_all(env)
    assert got["sparse"] == (pytest.approx(-2 / 3), False, 1)
    assert got["sparse_offset"] == (pytest.approx(-2 / 3 + 0.7), False, 1)
    for agent in a:  # all three on one spot: 3 pairs, 2 landmarks uncovered
        place(agent, 0.0, 0.0)
    assert evaluate_all(env)["sparse"] == (pytest.approx(-5 / 3), False, 3)
    place(a[0], -1.0, 0.05)
    place(a[1], 0.0, 0.0)
    place(a[2], 1.0, -0.05)
    assert evaluate_all(env)["sparse"] == (0.0, True, 0)
    env.close()


def test_speaker_listener_target_vs_other_landmark() -> None:
    env = make_task("speaker_listener", seed=4)
    env.reset()
    speaker, listener = env.world.agents
    assert listener.size == pytest.approx(0.075)
    assert all(lm.size == pytest.approx(0.04) for lm in env.world.landmarks)
    target = speaker.goal_b
    others = [lm for lm in env.world.landmarks if lm is not target]
    assert len(others) == 2
    place(target, 0.5, 0.5)
    place(others[0], -0.5, -0.5)
    place(others[1], 0.5, -0.5)
    place(listener, 0.5 + 0.1, 0.5)  # 0.1 < 0.075 + 0.04
    got = evaluate_all(env)
    assert got["sparse"] == (0.0, True, 0)
    assert got["sparse_offset"] == (pytest.approx(0.7), True, 0)
    place(listener, -0.5, -0.5)  # on a landmark, but not the target
    got = evaluate_all(env)
    assert got["sparse"] == (-1.0, False, 0)
    assert got["sparse_offset"] == (pytest.approx(-0.3), False, 0)
    place(listener, 0.5, 0.5 + 0.12)  # just outside the target
    assert evaluate_all(env)["sparse"] == (-1.0, False, 0)
    place(speaker, 0.5, 0.5)  # overlapping agents that do not collide
    place(listener, 0.5, 0.5)
    assert evaluate_all(env)["sparse"] == (0.0, True, 0)
    env.close()


def test_step_reward_is_evaluate_after_move() -> None:
    env = make_task("simple", reward="sparse_offset", seed=0)
    env.reset()
    agent, lm = env.world.agents[0], env.world.landmarks[0]
    place(lm, 0.0, 0.0)
    place(agent, 0.0, 0.0)
    agent.state.p_vel = np.array([2.0, 0.0])  # this step carries it 0.2 away
    res = env.step([np.zeros(2)])
    assert (res.reward, res.success, res.collisions) == (pytest.approx(-0.3), False, 0)
    env.close()


# --- dense reward -----------------------------------------------------------------------------


def reference_env(task: str):
    if task == "simple":
        return simple_v3.parallel_env(max_cycles=20, continuous_actions=True)
    if task == "spread":
        return simple_spread_v3.parallel_env(N=2, max_cycles=20, continuous_actions=True)
    return simple_speaker_listener_v4.parallel_env(max_cycles=20, continuous_actions=True)


@pytest.mark.parametrize("task", TASKS)
def test_dense_equals_mpe2_reward(task: str) -> None:
    env = make_task(task, reward="dense")
    ref = reference_env(task)
    obs = env.reset(seed=11)
    ref_obs, _ = ref.reset(seed=11)
    if task == "spread":  # same world as ours, thesis sizes included
        for e in ref.unwrapped.world.entities:
            e.size = 0.125
    for o, a in zip(obs, env.spec.agents, strict=True):
        np.testing.assert_array_equal(o, ref_obs[a.name])
    rng = np.random.default_rng(0)
    for _ in range(20):
        acts = [rng.uniform(a.act_low, a.act_high) for a in env.spec.agents]
        res = env.step(acts)
        _, ref_rew, _, _, _ = ref.step(
            {a.name: to_mpe_action(a, x) for a, x in zip(env.spec.agents, acts, strict=True)}
        )
        expected = float(np.mean([ref_rew[a.name] for a in env.spec.agents]))
        assert res.reward == pytest.approx(expected, rel=1e-9, abs=1e-12)
        assert env.evaluate()[0] == pytest.approx(res.reward, rel=1e-9, abs=1e-12)
        assert res.reward != -1.0 and res.reward != 0.0  # not the sparse reward
    env.close()
    ref.close()


# --- episodes and seeds -----------------------------------------------------------------------


@pytest.mark.parametrize("task", TASKS)
def test_truncated_only_on_last_step(task: str) -> None:
    env = make_task(task, seed=0)
    for _ in range(2):  # also after a reset
        env.reset()
        flags = [env.step(zero_actions(env)).truncated for _ in range(20)]
        assert flags == [False] * 19 + [True]
        with pytest.raises(RuntimeError):
            env.step(zero_actions(env))
    env.close()


def test_episode_len_is_configurable() -> None:
    env = make_task("spread", episode_len=3, seed=0)
    env.reset()
    assert [env.step(zero_actions(env)).truncated for _ in range(3)] == [False, False, True]
    env.close()


@pytest.mark.parametrize("task", TASKS)
def test_seed_reproducible(task: str) -> None:
    a = make_task(task)
    b = make_task(task, seed=7)
    first_a = a.reset(seed=7)
    first_b = b.reset()  # the constructor's seed
    for x, y in zip(first_a, first_b, strict=True):
        np.testing.assert_array_equal(x, y)
    # Unseeded resets continue the same RNG stream in both envs...
    second_a, second_b = a.reset(), b.reset()
    for x, y in zip(second_a, second_b, strict=True):
        np.testing.assert_array_equal(x, y)
    # ... and give a new episode, while reseeding replays the first.
    assert any(not np.array_equal(x, y) for x, y in zip(first_a, second_a, strict=True))
    for x, y in zip(a.reset(seed=7), first_a, strict=True):
        np.testing.assert_array_equal(x, y)
    c = make_task(task)
    d = make_task(task)
    assert any(
        not np.array_equal(x, y) for x, y in zip(c.reset(seed=1), d.reset(seed=2), strict=True)
    )
    for env in (a, b, c, d):
        env.close()


def test_all_rewards_run_on_all_tasks() -> None:
    for task in TASKS:
        for kind in REWARDS:
            env = make_task(task, reward=kind, seed=0)
            env.reset()
            res = env.step(zero_actions(env))
            assert isinstance(res.reward, float) and isinstance(res.success, bool)
            assert isinstance(res.collisions, int)
            env.close()


@pytest.mark.parametrize(
    ("task", "agents", "reward"),
    [
        ("simple", 1, "sparse"),
        ("simple", 1, "dense"),
        ("spread", 2, "dense"),
        ("spread", 3, "sparse"),
        ("spread", 4, "sparse"),
        ("speaker_listener", 2, "dense"),
        ("speaker_listener", 2, "sparse_offset"),
    ],
)
def test_direct_step_equals_the_pettingzoo_api(task: str, agents: int, reward: str) -> None:
    """The default direct path and PettingZoo's parallel step agree bit for bit, over
    several episodes of random (also out-of-range) actions, through resets, whether
    the direct env is stepped per agent or by the joint action."""
    direct = make_task(task, agents, reward, episode_len=7, seed=5)
    api = make_task(task, agents, reward, episode_len=7, seed=5, direct=False)
    assert direct.direct and not api.direct
    rng = np.random.default_rng(0)
    for episode in range(3):
        for a, b in zip(direct.reset(), api.reset(), strict=True):
            np.testing.assert_array_equal(a, b)
        for t in range(7):
            actions = [
                rng.uniform(-1.5, 1.5, spec.act_dim).astype(np.float32)
                for spec in direct.spec.agents
            ]
            if t == 3:  # signed zeros, huge and subnormal values
                special = np.array([-0.0, 0.0, 1e30, -1e30, 1e-40, -1e-40], np.float32)
                actions = [rng.choice(special, a.shape) for a in actions]
            if t % 2:  # the joint step (collection, evaluation) and the per-agent one
                j = direct.step_joint(np.concatenate(actions))
                x = StepResult(list(np.split(j.obs, np.cumsum(direct.spec.obs_dims)[:-1])), *j[1:])
            else:
                x = direct.step(actions)
            y = api.step(actions)
            for a, b in zip(x.obs, y.obs, strict=True):
                np.testing.assert_array_equal(a, b)
            for p, q in zip(direct.world.agents, api.world.agents, strict=True):
                for field in ("p_pos", "p_vel", "c"):
                    u, v = getattr(p.state, field), getattr(q.state, field)
                    assert u.dtype == v.dtype and u.tobytes() == v.tobytes(), (field, t)
            assert (x.reward, x.success, x.collisions, x.truncated) == (
                y.reward,
                y.success,
                y.collisions,
                y.truncated,
            ), (episode, t)
        assert x.truncated
        with pytest.raises(RuntimeError, match="episode is over"):
            direct.step(actions)


def test_joint_step_refuses_bad_actions_and_names_the_agent() -> None:
    env = make_task("speaker_listener", seed=0)
    with pytest.raises(RuntimeError, match="call reset"):
        env.step_joint(np.zeros(env.spec.joint_act_dim, np.float32))
    env.reset()
    with pytest.raises(ValueError, match="joint action has 4 values, expected 5"):
        env.step_joint(np.zeros(4, np.float32))
    bad = np.zeros(env.spec.joint_act_dim, np.float32)
    bad[-1] = np.nan  # the listener's movement
    with pytest.raises(ValueError, match="non-finite action of listener_0"):
        env.step_joint(bad)
    with pytest.raises(ValueError, match="speaker_0: action has shape"):
        env.step([np.zeros(2, np.float32), np.zeros(2, np.float32)])
    res = env.step_joint(np.zeros(env.spec.joint_act_dim, np.float32))  # nothing was lost
    assert res.obs.shape == (env.spec.joint_obs_dim,) and res.obs.dtype == np.float32


def test_joint_step_clips_actions_into_the_box() -> None:
    """An out-of-range action moves the world exactly as its clipped version does."""
    wild, tame = (make_task("speaker_listener", seed=3) for _ in range(2))
    wild.reset(), tame.reset()
    rng = np.random.default_rng(4)
    low = np.concatenate([a.act_low for a in wild.spec.agents]).astype(np.float32)
    high = np.concatenate([a.act_high for a in wild.spec.agents]).astype(np.float32)
    for _ in range(5):
        action = rng.uniform(-3, 3, wild.spec.joint_act_dim).astype(np.float32)
        x, y = wild.step_joint(action), tame.step_joint(np.clip(action, low, high))
        np.testing.assert_array_equal(x.obs, y.obs)
        assert x[1:] == y[1:]
    listener = wild.world.agents[1]
    assert np.abs(listener.state.p_vel).max() > 0  # the steps did move it


# --- task options of profile thesis (docs/fidelity.md) ----------------------------------------


def test_success_terminal_ends_the_world_and_the_window_goes_on() -> None:
    """A success step is terminal with its own observation; the next world is new and the
    episode still ends at its 20th step (the thesis code's fixed windows)."""
    env = make_task("simple", seed=0, success_terminal=True)
    env.reset()
    agent, lm = env.world.agents[0], env.world.landmarks[0]
    flags = [env.step(zero_actions(env)) for _ in range(4)]
    assert not any(r.terminated or r.success for r in flags)  # seed 0 starts 1.3 apart
    place(lm, 0.3, 0.3)
    place(agent, 0.3, 0.3)
    res = env.step(zero_actions(env))
    assert res.success and res.terminated and not res.truncated
    np.testing.assert_array_equal(res.obs[0], np.zeros(4, np.float32))  # on the landmark
    with pytest.raises(RuntimeError, match="reset_world"):
        env.step(zero_actions(env))
    fresh = env.reset_world()[0]
    assert not np.array_equal(lm.state.p_pos, [0.3, 0.3])  # a new world ...
    assert not np.array_equal(agent.state.p_pos, [0.3, 0.3])
    np.testing.assert_allclose(fresh[2:], lm.state.p_pos - agent.state.p_pos, rtol=1e-6)
    assert np.linalg.norm(fresh[2:]) >= 0.1  # ... not already a success (seed 0)
    rest = [env.step(zero_actions(env)) for _ in range(15)]  # steps 6..20
    assert [r.truncated for r in rest] == [False] * 14 + [True]
    with pytest.raises(RuntimeError, match="time limit"):
        env.step(zero_actions(env))
    env.close()
    plain = make_task("simple", seed=0)  # the default: success is not terminal
    plain.reset()
    place(plain.world.landmarks[0], 0.3, 0.3)
    place(plain.world.agents[0], 0.3, 0.3)
    res = plain.step(zero_actions(plain))
    assert res.success and not res.terminated
    assert plain.step(zero_actions(plain)).success  # the same world goes on
    plain.close()


def test_success_terminal_at_the_last_step_needs_no_world_reset() -> None:
    env = make_task("spread", episode_len=2, seed=0, success_terminal=True)
    env.reset()
    env.step(zero_actions(env))
    (a0, a1), (l0, l1) = env.world.agents, env.world.landmarks
    place(l0, 0.0, 0.0), place(l1, 1.0, 0.0), place(a0, 0.0, 0.0), place(a1, 1.0, 0.0)
    res = env.step(zero_actions(env))
    assert res.terminated and res.truncated
    env.reset()  # the ordinary reset starts the next episode
    assert not env.step(zero_actions(env)).truncated
    env.close()


def test_cover_landmark_counts_a_landmark_within_its_own_size_for_the_reward_only() -> None:
    """Rows T8/T11: the reward's cover radius is 0.125 (the landmark), success's 0.25."""
    envs = {c: make_task("spread", agents=2, seed=0, cover=c) for c in ("sum", "landmark")}
    for env in envs.values():
        env.reset()
        (a0, a1), (l0, l1) = env.world.agents, env.world.landmarks
        place(l0, 0.0, 0.0)
        place(l1, 1.0, 0.0)
        place(a0, 0.1, 0.0)
        place(a1, 1.0, 0.2)  # landmark 1 at 0.2: < 0.25, > 0.125
    assert evaluate_all(envs["sum"])["sparse"] == (0.0, True, 0)
    assert evaluate_all(envs["landmark"])["sparse"] == (-0.5, True, 0)
    assert envs["landmark"].evaluate() == (pytest.approx(-0.5 + 0.7), True, 0)  # offset too
    # The thesis code calls a landmark uncovered when min_dist > size: 0.125 still covers.
    place(envs["landmark"].world.agents[1], 1.125, 0.0)
    assert evaluate_all(envs["landmark"])["sparse"] == (0.0, True, 0)
    place(envs["landmark"].world.agents[0], 0.2, 0.0)  # landmark 0 at 0.2 too
    assert evaluate_all(envs["landmark"])["sparse"] == (-0.5, True, 0)
    for env in envs.values():
        env.close()
    # The other tasks use the sum in the thesis code as well: cover changes nothing there.
    sl = make_task("speaker_listener", seed=4, cover="landmark")
    sl.reset()
    speaker, listener = sl.world.agents
    place(speaker.goal_b, 0.5, 0.5)
    place(listener, 0.6, 0.5)  # 0.1 < 0.075 + 0.04, > 0.04
    assert sl.evaluate() == (0.0, True, 0)
    sl.close()


def test_landmark_size_sets_the_worlds_landmarks_and_the_success_radius() -> None:
    """Rows T6/T7: speaker_listener's landmarks at the thesis code's 0.075, so covering
    and success are within 0.15 instead of 0.115; the agents keep their sizes."""
    sizes = {}
    for size in (None, 0.075):
        env = make_task("speaker_listener", seed=4, landmark_size=size, success_terminal=True)
        env.reset()
        for _ in range(2):
            speaker, listener = env.world.agents
            sizes[size] = [lm.size for lm in env.world.landmarks]
            assert (speaker.size, listener.size) == (0.075, 0.075)
            place(speaker.goal_b, 0.5, 0.5)
            place(listener, 0.5 + 0.14, 0.5)  # 0.115 < 0.14 < 0.15
            assert env.evaluate() == ((0.0, True, 0) if size else (-1.0, False, 0))
            env.reset_world()  # sizes hold in a new world too
        env.close()
    assert sizes == {None: [0.04] * 3, 0.075: [0.075] * 3}
    spread = make_task("spread", agents=2, seed=0, landmark_size=0.05)
    for _ in range(2):
        spread.reset()
        assert [e.size for e in spread.world.agents] == [0.125, 0.125]
        assert [e.size for e in spread.world.landmarks] == [0.05, 0.05]
    (a0, a1), (l0, l1) = spread.world.agents, spread.world.landmarks
    place(l0, 0.0, 0.0), place(l1, 1.0, 0.0), place(a0, 0.0, 0.0), place(a1, 1.0, 0.2)
    assert spread.evaluate() == (-0.5, False, 0)  # 0.2 > 0.125 + 0.05
    spread.close()
    with pytest.raises(ValueError, match="landmark_size"):
        make_task("simple", landmark_size=0.0)


def test_pad_obs_pads_the_speaker_with_zeros_to_the_listeners_size() -> None:
    """Row T4: the speaker's 3 colour values then 8 zeros; the listener unchanged."""
    spec = task_spec("speaker_listener", pad_obs=True)
    assert spec.obs_dims == (11, 11) and spec.joint_obs_dim == 22
    assert spec.agents[0].obs_layout == "goal_colour(3) zero_pad(8)"
    assert spec.act_dims == (3, 2)
    for direct in (True, False):
        padded = make_task("speaker_listener", seed=3, pad_obs=True, direct=direct)
        plain = make_task("speaker_listener", seed=3, direct=direct)
        assert padded.spec == spec
        obs_p, obs_0 = padded.reset(), plain.reset()
        rng = np.random.default_rng(1)
        for t in range(4):
            assert [o.shape for o in obs_p] == [(11,), (11,)]
            assert all(o.dtype == np.float32 for o in obs_p)
            np.testing.assert_array_equal(obs_p[0][:3], obs_0[0])
            assert np.any(obs_p[0][:3] > 0.5)  # the target's colour is there
            np.testing.assert_array_equal(obs_p[0][3:], np.zeros(8, np.float32))
            np.testing.assert_array_equal(obs_p[1], obs_0[1])
            acts = [rng.uniform(a.act_low, a.act_high).astype(np.float32) for a in spec.agents]
            if t % 2:
                obs_p, obs_0 = padded.step(acts).obs, plain.step(acts).obs
            else:
                j = padded.step_joint(np.concatenate(acts)).obs
                obs_p, obs_0 = [j[:11], j[11:]], plain.step(acts).obs
        assert np.abs(obs_p[1][-3:]).max() > 0  # the message reached the listener
    # Equal sizes already: padding changes nothing.
    assert task_spec("spread", agents=3, pad_obs=True) == task_spec("spread", agents=3)


@pytest.mark.parametrize("n", [2, 3])
def test_comm_obs_false_drops_spreads_always_zero_comm_slots(n: int) -> None:
    """Row T3: 10 values per agent for N=2 (the thesis code's layout), 4N + 2 in general."""
    spec = task_spec("spread", agents=n, comm_obs=False)
    assert spec.obs_dims == (4 * n + 2,) * n
    assert "other_comm_zero" not in spec.agents[0].obs_layout
    both = make_task("spread", agents=n, seed=2, comm_obs=False), make_task("spread", agents=n)
    short, full = both
    assert short.spec == spec
    obs_s, obs_f = short.reset(), full.reset(seed=2)
    for _ in range(3):
        for s, f in zip(obs_s, obs_f, strict=True):
            assert s.shape == (4 * n + 2,)
            np.testing.assert_array_equal(s, f[: 4 * n + 2])
            np.testing.assert_array_equal(f[4 * n + 2 :], np.zeros(2 * (n - 1), np.float32))
        acts = [np.full(2, 0.4, np.float32)] * n
        obs_s, obs_f = short.step(acts).obs, full.step(acts).obs
    # The other tasks have no such slots (the listener's message is a real one).
    assert task_spec("speaker_listener", comm_obs=False) == task_spec("speaker_listener")
    for env in both:
        env.close()


def test_velocity_first_integrator_moves_with_the_new_velocity_by_hand() -> None:
    """Row T16: one step by hand. Velocity-first (the thesis code): v' = 0.75 v + 0.1 * 5 a,
    then p' = p + 0.1 v'. mpe2's position-first: p' = p + 0.1 v, the same v'."""
    a = np.array([0.3, -0.6])
    p, v = np.array([0.3, -0.2]), np.array([0.4, 0.1])
    v_new = v * (1 - 0.25) + (a * SENSITIVITY / 1.0) * 0.1  # (0.45, -0.225)
    expected = {"velocity-first": p + v_new * 0.1, "position-first": p + v * 0.1}
    for integrator, p_new in expected.items():
        for direct in (True, False):
            env = make_task("simple", seed=0, integrator=integrator, direct=direct)
            env.reset()
            agent, lm = env.world.agents[0], env.world.landmarks[0]
            place(lm, 0.0, 0.0)
            agent.state.p_pos, agent.state.p_vel = p.copy(), v.copy()
            res = env.step([a.astype(np.float32)])
            np.testing.assert_allclose(agent.state.p_vel, v_new, rtol=1e-6)
            np.testing.assert_allclose(agent.state.p_pos, p_new, rtol=1e-6)
            np.testing.assert_allclose(res.obs[0][2:], -p_new, rtol=1e-6)
            env.close()
    assert not np.allclose(expected["velocity-first"], expected["position-first"])


def test_velocity_first_keeps_mpe2s_contact_forces() -> None:
    """Two overlapping spread agents push apart under either order (the force is the same,
    only when it moves them differs)."""
    moved = {}
    for integrator in INTEGRATORS:
        env = make_task("spread", agents=2, seed=0, integrator=integrator)
        env.reset()
        a0, a1 = env.world.agents
        place(a0, 0.0, 0.0)
        place(a1, 0.1, 0.0)
        env.step(zero_actions(env))
        moved[integrator] = a1.state.p_pos[0] - 0.1
        env.close()
    assert moved["position-first"] == 0.0  # moves one step later
    assert moved["velocity-first"] > 0.0


def test_thesis_options_direct_step_equals_the_pettingzoo_api() -> None:
    """Every task option at once, through a forced success and its new world: the direct
    path and PettingZoo's step agree bit for bit."""
    opts = dict(
        success_terminal=True,
        cover="landmark",
        landmark_size=0.075,
        pad_obs=True,
        comm_obs=False,
        integrator="velocity-first",
    )
    for task in TASKS:
        direct = make_task(task, 2, "sparse", episode_len=8, seed=5, **opts)
        api = make_task(task, 2, "sparse", episode_len=8, seed=5, direct=False, **opts)
        rng = np.random.default_rng(0)
        terminal = 0
        for _ in range(2):
            for a, b in zip(direct.reset(), api.reset(), strict=True):
                np.testing.assert_array_equal(a, b)
            for t in range(8):
                if t == 3:  # every landmark under an agent: a success
                    for env in (direct, api):
                        for ag, lm in zip(env.world.agents[-1:], env.world.landmarks):
                            place(lm, *ag.state.p_pos)
                        if task == "spread":
                            place(env.world.landmarks[1], *env.world.agents[1].state.p_pos)
                        if task == "speaker_listener":
                            place(env.world.agents[0].goal_b, *env.world.agents[1].state.p_pos)
                acts = [
                    rng.uniform(-1.5, 1.5, s.act_dim).astype(np.float32) for s in direct.spec.agents
                ]
                if t == 3:
                    acts = [np.zeros_like(x) for x in acts]
                x, y = direct.step(acts), api.step(acts)
                for a, b in zip(x.obs, y.obs, strict=True):
                    np.testing.assert_array_equal(a, b)
                assert (x.reward, x.success, x.terminated, x.truncated) == (
                    y.reward,
                    y.success,
                    y.terminated,
                    y.truncated,
                )
                if x.terminated and not x.truncated:
                    terminal += 1
                    for a, b in zip(direct.reset_world(), api.reset_world(), strict=True):
                        np.testing.assert_array_equal(a, b)
        assert terminal >= 2, task
        direct.close()
        api.close()


@pytest.mark.parametrize("profile", ["mpe2", "thesis"])
def test_task_spec_for_a_config_equals_its_envs_spec(profile: str) -> None:
    """The learner and the counter size from `task_spec_for`, the actors step
    `make_task_for`: the two must agree on every option that changes a shape."""
    from shared.config import make_config

    for task, algo in (
        ("simple", "ddpg"),
        ("spread", "cen-maddpg"),
        ("speaker_listener", "cen-maddpg"),
    ):
        cfg = make_config({"task": task, "algo": algo, "profile": profile})
        env = make_task_for(cfg, seed=0)
        assert task_spec_for(cfg) == env.spec
        assert [o.shape[0] for o in env.reset()] == list(env.spec.obs_dims)
        env.close()
    dims = task_spec_for(make_config({"profile": profile})).obs_dims
    assert dims == {"mpe2": (3, 11), "thesis": (11, 11)}[profile]
