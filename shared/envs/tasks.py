"""Task adapters: the thesis's three particle tasks on top of mpe2's PettingZoo parallel API.

mpe2 gives the worlds, physics and observations; this module adds what the thesis changed:

* a 2-D movement action in [-1, 1] (mpe2 wants a 5-vector in [0, 1]), so policies and the
  SimHash vectors o_i || a_i have the thesis's sizes;
* sparse rewards ("sparse", "sparse_offset") computed from the world state, with mpe2's own
  dense reward kept as an option;
* success and collision measures, which the metrics need at every step;
* agent and landmark size 0.125 in the navigation task (the thesis's original code);
* the task-level options of `profile: thesis` (docs/fidelity.md), each off by default:
  success as a terminal step with a new world, the sparse reward's cover radius, a
  landmark size, zero-padded or comm-free observations, and the thesis code's order of
  velocity and position updates.

A task named `package.module:factory` is any PettingZoo ParallelEnv with Box spaces,
adapted by shared/envs/custom_task.py behind the same interface (`make_task_for`,
`task_spec_for` dispatch), so no caller has a special case.

See docs/tasks.md for the layouts and the hashed vector sizes.
"""

from __future__ import annotations

import functools
import types
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
from mpe2 import simple_speaker_listener_v4, simple_spread_v3, simple_v3
from mpe2._mpe_utils.core import Agent, Entity, World

from shared.core.joint import offsets
from shared.envs.spec import AgentSpec, JointStep, StepResult, TaskSpec

TASKS = ("simple", "spread", "speaker_listener")
REWARDS = ("sparse", "sparse_offset", "dense")
COVERS = ("sum", "landmark")
INTEGRATORS = ("position-first", "velocity-first")

#: Added to the sparse reward by "sparse_offset" (the thesis's shifted navigation reward).
SPARSE_OFFSET = 0.7
#: Agent and landmark radius in the navigation task, as in the thesis's original code.
SPREAD_ENTITY_SIZE = 0.125
#: Width of the thesis's movement action (x, y); mpe2 expands it to 2 * 2 + 1 values.
MOVE_DIM = 2

_FIXED_AGENTS = {"simple": 1, "speaker_listener": 2}


def _check_task(task: str, agents: int, episode_len: int) -> int:
    """Validate arguments; return the real agent count (fixed for simple and speaker_listener)."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")
    if episode_len < 1:
        raise ValueError(f"episode_len must be >= 1, got {episode_len}")
    if task in _FIXED_AGENTS:
        return _FIXED_AGENTS[task]  # `agents` only sizes the navigation task
    if agents < 1:
        raise ValueError(f"spread needs at least one agent, got {agents}")
    return agents


def _make_parallel(task: str, n_agents: int, episode_len: int) -> Any:
    """Build the mpe2 parallel env with continuous actions."""
    if task == "simple":
        return simple_v3.parallel_env(max_cycles=episode_len, continuous_actions=True)
    if task == "spread":
        return simple_spread_v3.parallel_env(
            N=n_agents, max_cycles=episode_len, continuous_actions=True
        )
    return simple_speaker_listener_v4.parallel_env(max_cycles=episode_len, continuous_actions=True)


def _resize_for_task(task: str, world: World, landmark_size: float | None = None) -> None:
    """Apply the thesis's entity sizes (navigation only; the others keep mpe2's), then the
    landmark radius asked for, if any. mpe2 sets sizes only when it builds a world, so
    setting them on its world is enough; covering and success read them from there."""
    if task == "spread":
        for entity in world.entities:
            entity.size = SPREAD_ENTITY_SIZE
    if landmark_size is not None:
        for landmark in world.landmarks:
            landmark.size = landmark_size


def integrate_velocity_first(world: World, p_force: list[Any]) -> None:
    """The thesis code's integration (its `ma_envs/multiagent/core.py:164-175`): damp the
    velocity, add the force, cap the speed, then move with the *new* velocity. mpe2's own
    `integrate_state` moves with the old velocity first, so there a force moves an agent
    one step later. Bound onto an mpe2 World, which calls it from its `step`."""
    for i, entity in enumerate(world.entities):
        if not entity.movable:
            continue
        state = entity.state
        state.p_vel = state.p_vel * (1 - world.damping)
        force = p_force[i]
        if force is not None:
            state.p_vel += (force / entity.mass) * world.dt
        if entity.max_speed is not None:
            speed = np.sqrt(np.square(state.p_vel[0]) + np.square(state.p_vel[1]))
            if speed > entity.max_speed:
                state.p_vel = state.p_vel / speed * entity.max_speed
        state.p_pos += state.p_vel * world.dt


def _set_integrator(world: World, integrator: str) -> None:
    """Velocity-first replaces the world's integration step on this world only."""
    if integrator == "velocity-first":
        bound = types.MethodType(integrate_velocity_first, world)
        world.integrate_state = bound


def _obs_layout(task: str, agent: Agent, world: World) -> list[tuple[str, int]]:
    """Named blocks of an agent's mpe2 observation, in order."""
    n_agents, n_landmarks, dim_p = len(world.agents), len(world.landmarks), world.dim_p
    if task == "simple":
        return [("self_vel", dim_p), ("landmark_rel", dim_p * n_landmarks)]
    if task == "spread":
        return [
            ("self_vel", dim_p),
            ("self_pos", dim_p),
            ("landmark_rel", dim_p * n_landmarks),
            ("other_rel", dim_p * (n_agents - 1)),
            ("other_comm_zero", world.dim_c * (n_agents - 1)),
        ]
    if not agent.movable:  # the speaker sees only the target's colour
        return [("goal_colour", world.dim_color)]
    return [
        ("self_vel", dim_p),
        ("landmark_rel", dim_p * n_landmarks),
        ("speaker_message", world.dim_c),
    ]


def _shaped_layouts(
    task: str, env: Any, pad_obs: bool, comm_obs: bool
) -> list[tuple[list[tuple[str, int]], int]]:
    """Each agent's observation blocks as the learners see them, and how many leading
    values of mpe2's observation they keep (the rest are zeros).

    comm_obs=False drops spread's trailing always-zero communication slots (the thesis
    code has none); pad_obs appends zeros up to the largest agent's size (the thesis
    code's speaker: 3 values then 8 zeros, since its buffers hold one size for all)."""
    world: World = env.unwrapped.world
    shaped = []
    for name, agent in zip(env.possible_agents, world.agents, strict=True):
        blocks = _obs_layout(task, agent, world)
        obs_dim = int(env.observation_space(name).shape[0])
        if sum(size for _, size in blocks) != obs_dim:
            raise RuntimeError(f"mpe2 observation of {name} ({obs_dim}) differs from {blocks}")
        if not comm_obs and blocks[-1][0] == "other_comm_zero":
            blocks = blocks[:-1]
        shaped.append((blocks, sum(size for _, size in blocks)))
    width = max(keep for _, keep in shaped)
    if pad_obs:
        shaped = [
            (blocks + [("zero_pad", width - keep)] if keep < width else blocks, keep)
            for blocks, keep in shaped
        ]
    return shaped


def _specs_from_env(
    task: str, env: Any, pad_obs: bool = False, comm_obs: bool = True
) -> tuple[AgentSpec, ...]:
    """Read each agent's sizes from a built env and cross-check them against the layouts."""
    world: World = env.unwrapped.world
    specs = []
    shaped = _shaped_layouts(task, env, pad_obs, comm_obs)
    for name, agent, (blocks, _) in zip(env.possible_agents, world.agents, shaped, strict=True):
        obs_dim = sum(size for _, size in blocks)
        low: list[float] = []
        high: list[float] = []
        act_parts = []
        if agent.movable:
            low += [-1.0] * MOVE_DIM
            high += [1.0] * MOVE_DIM
            act_parts.append(f"move_xy({MOVE_DIM}) in [-1,1]")
        if not agent.silent:
            low += [0.0] * world.dim_c
            high += [1.0] * world.dim_c
            act_parts.append(f"message({world.dim_c}) in [0,1]")
        specs.append(
            AgentSpec(
                name=name,
                obs_dim=obs_dim,
                act_low=tuple(low),
                act_high=tuple(high),
                obs_layout=" ".join(f"{n}({s})" for n, s in blocks),
                act_layout=" ".join(act_parts),
            )
        )
    return tuple(specs)


@functools.cache
def _agent_specs(
    task: str, n_agents: int, pad_obs: bool = False, comm_obs: bool = True
) -> tuple[AgentSpec, ...]:
    """Build a throwaway env once per (task, agents, observation options): sizes then come
    from mpe2 itself."""
    env = _make_parallel(task, n_agents, episode_len=1)
    try:
        return _specs_from_env(task, env, pad_obs, comm_obs)
    finally:
        env.close()


def task_spec(
    task: str,
    agents: int = 2,
    episode_len: int = 20,
    *,
    pad_obs: bool = False,
    comm_obs: bool = True,
) -> TaskSpec:
    """Shapes of a task without keeping an env (for sizing networks in learners).

    Takes the two options that change observation sizes; the other task options of
    `make_task` change values, not shapes."""
    n_agents = _check_task(task, agents, episode_len)
    specs = _agent_specs(task, n_agents, pad_obs, comm_obs)
    return TaskSpec(name=task, agents=specs, episode_len=episode_len)


@functools.cache
def _bounds(agent: AgentSpec) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(agent.act_low, np.float32), np.asarray(agent.act_high, np.float32)


def to_mpe_action(agent: AgentSpec, action: np.ndarray) -> np.ndarray:
    """Map a thesis-layout action onto mpe2's layout after clipping it to the agent's bounds.

    Movement (x, y) becomes [0, max(-x,0), max(x,0), max(-y,0), max(y,0)], so mpe2's force
    (pair differences times the sensitivity) is exactly (x, y) times the sensitivity. A
    message passes through. float32 matches mpe2's Box, which otherwise warns and clips.
    """
    a = np.asarray(action, dtype=np.float32).reshape(-1)
    if a.shape[0] != agent.act_dim:
        raise ValueError(f"{agent.name}: action has {a.shape[0]} values, expected {agent.act_dim}")
    if not np.isfinite(a).all():
        raise ValueError(f"{agent.name}: non-finite action {a}")
    low, high = _bounds(agent)
    a = np.minimum(np.maximum(a, low), high)
    n_move = agent.move_dim
    if not n_move:
        return a
    out = np.zeros(1 + 2 * n_move + a.shape[0] - n_move, np.float32)
    move = a[:n_move]
    out[1 : 1 + 2 * n_move : 2] = np.maximum(-move, 0.0)
    out[2 : 2 + 2 * n_move : 2] = np.maximum(move, 0.0)
    out[1 + 2 * n_move :] = a[n_move:]
    return out


def _dist(a: Entity, b: Entity) -> float:
    return float(np.sqrt(np.sum(np.square(a.state.p_pos - b.state.p_pos))))


def covers(agent: Entity, landmark: Entity) -> bool:
    """An agent covers a landmark when their centres are closer than the sum of their radii."""
    return _dist(agent, landmark) < agent.size + landmark.size


def count_collisions(world: World) -> int:
    """Colliding agent pairs: both agents collide and are closer than the sum of their radii."""
    agents = [a for a in world.agents if a.collide]
    return sum(
        1 for i, a in enumerate(agents) for b in agents[i + 1 :] if _dist(a, b) < a.size + b.size
    )


def _sparse_simple(world: World) -> tuple[float, bool]:
    ok = covers(world.agents[0], world.landmarks[0])
    return (0.0 if ok else -1.0), ok


def _sparse_spread(world: World, landmark_cover: bool = False) -> tuple[float, bool]:
    """Success needs every landmark covered (sum of radii). With `landmark_cover` the
    reward counts a landmark covered when an agent is within the landmark's own radius,
    as the thesis code's reward does (`min_dist > size` is uncovered, so `<=` covers),
    a different radius from its success test."""
    uncovered = sum(1 for lm in world.landmarks if not any(covers(a, lm) for a in world.agents))
    if landmark_cover:
        rewarded_uncovered = sum(
            1 for lm in world.landmarks if not any(_dist(a, lm) <= lm.size for a in world.agents)
        )
    else:
        rewarded_uncovered = uncovered
    collisions = count_collisions(world)
    return -(rewarded_uncovered + collisions) / len(world.agents), uncovered == 0


def _sparse_speaker_listener(world: World) -> tuple[float, bool]:
    speaker, listener = world.agents[0], world.agents[1]
    ok = covers(listener, speaker.goal_b)
    return (0.0 if ok else -1.0), ok


_SPARSE: dict[str, Callable[[World], tuple[float, bool]]] = {
    "simple": _sparse_simple,
    "spread": _sparse_spread,
    "speaker_listener": _sparse_speaker_listener,
}


class TaskEnv:
    """Wraps one mpe2 parallel env and speaks the thesis's action layout and rewards.

    `step` drives mpe2's own env object directly by default (`direct=True`): it sets all
    agents' actions as mpe2's `_set_action` does and runs mpe2's world step and
    observations, which is what PettingZoo's parallel `step` ends up doing after passing
    each action through the AEC cycle and four wrappers (order enforcing, bounds
    clipping, the parallel conversion). Those layers cost most of a step, and the
    evaluator runs ten episodes per training episode. `step_joint` takes and gives joint
    vectors (what collection and evaluation hold), so no per-agent split and join either
    (docs/performance.md, "Evaluation and collection", has the cost of each path).
    tests/test_tasks.py checks that the paths give the same observations, rewards and
    ends, bit for bit.
    `direct=False` steps through the public API; `reset` always does.

    The keyword options are the task-level choices of `profile: thesis` (shared/config.py
    describes each; docs/fidelity.md rows T3, T4, T6-T8, T12, T16). Their defaults are
    mpe2's behaviour with the adapter's changes above.
    """

    spec: TaskSpec

    def __init__(
        self,
        task: str,
        agents: int = 2,
        reward: str = "sparse",
        episode_len: int = 20,
        seed: int | None = None,
        direct: bool = True,
        *,
        success_terminal: bool = False,
        cover: str = "sum",
        landmark_size: float | None = None,
        pad_obs: bool = False,
        comm_obs: bool = True,
        integrator: str = "position-first",
    ) -> None:
        n_agents = _check_task(task, agents, episode_len)
        if reward not in REWARDS:
            raise ValueError(f"unknown reward {reward!r}; expected one of {REWARDS}")
        if cover not in COVERS:
            raise ValueError(f"unknown cover {cover!r}; expected one of {COVERS}")
        if integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {integrator!r}; expected one of {INTEGRATORS}")
        if landmark_size is not None and not landmark_size > 0:
            raise ValueError(f"landmark_size must be > 0, got {landmark_size}")
        self.task = task
        self.reward_kind = reward
        self.success_terminal = success_terminal
        self.landmark_size = landmark_size
        self._landmark_cover = cover == "landmark" and task == "spread"
        self._velocity_first = integrator == "velocity-first"
        self._env = _make_parallel(task, n_agents, episode_len)
        self._raw = self._env.unwrapped
        _resize_for_task(task, self._raw.world, landmark_size)
        _set_integrator(self._raw.world, integrator)
        self.spec = TaskSpec(task, _agent_specs(task, n_agents, pad_obs, comm_obs), episode_len)
        if tuple(a.name for a in self.spec.agents) != tuple(self._env.possible_agents):
            raise RuntimeError("agent order differs between spec and env")
        # The constructor's seed is used by the first reset() that brings none, so that
        # make_task(seed=s).reset() equals make_task().reset(seed=s).
        self._pending_seed = seed
        self._t: int | None = None  # steps taken this episode; None until reset
        self._world_ended = False  # success ended this world; reset_world() before stepping
        self.direct = direct
        spec = self.spec
        if [a.name for a in self._raw.world.agents] != [a.name for a in spec.agents]:
            raise RuntimeError("agent order differs between spec and mpe2's world")
        self._low = np.concatenate([_bounds(a)[0] for a in spec.agents])
        self._high = np.concatenate([_bounds(a)[1] for a in spec.agents])
        self._act_total, self._obs_total = spec.joint_act_dim, spec.joint_obs_dim
        act_off, obs_off = offsets(spec.act_dims), offsets(spec.obs_dims)
        self._act_split, self._obs_split = act_off[1:-1], obs_off[1:-1]
        self._act_slices = list(zip(act_off[:-1], act_off[1:], strict=True))
        self._obs_slices = list(zip(obs_off[:-1], obs_off[1:], strict=True))
        self._move_dims = [a.move_dim for a in spec.agents]
        # How many leading values of each mpe2 observation are kept; the rest of the
        # agent's block is zero padding. Equal to mpe2's sizes under the defaults.
        self._keep = [keep for _, keep in _shaped_layouts(task, self._env, pad_obs, comm_obs)]
        self._reshaped = self._keep != list(spec.obs_dims) or any(
            keep != int(self._env.observation_space(a.name).shape[0])
            for a, keep in zip(spec.agents, self._keep, strict=True)
        )

    @property
    def world(self) -> World:
        """The live mpe2 World (tests and debugging place entities through it)."""
        return self._raw.world

    def _shape(self, i: int, o: np.ndarray) -> np.ndarray:
        """Agent i's observation as the spec has it (comm slots dropped, zeros padded)."""
        o = np.asarray(o, dtype=np.float32)
        if not self._reshaped:
            return o
        out = np.zeros(self.spec.agents[i].obs_dim, np.float32)
        keep = self._keep[i]
        out[:keep] = o[:keep]
        return out

    def reset(self, seed: int | None = None) -> list[np.ndarray]:
        """Start an episode; a seed reseeds mpe2's RNG, no seed continues it."""
        if seed is None:
            seed, self._pending_seed = self._pending_seed, None
        else:
            self._pending_seed = None
        obs, _ = self._env.reset(seed=seed)
        _resize_for_task(self.task, self._raw.world, self.landmark_size)
        self._t = 0
        self._world_ended = False
        return [self._shape(i, obs[a.name]) for i, a in enumerate(self.spec.agents)]

    def rng_state(self) -> dict[str, Any]:
        """mpe2's RNG state (JSON-able): with it, a restored env's next `reset()` draws
        the world this one would have drawn (what a resumed run needs at an episode
        boundary; the world itself is not saved, the next episode starts with a reset)."""
        if self._pending_seed is not None:
            raise RuntimeError("reset the env once before saving its RNG state")
        return dict(self._raw.np_random.bit_generator.state)

    def set_rng_state(self, state: dict[str, Any]) -> None:
        self._pending_seed = None
        self._raw.np_random.bit_generator.state = state

    def reset_world(self) -> list[np.ndarray]:
        """A new world inside the running episode: mpe2's `reset_world` (new positions and
        goal, its RNG continuing), while the step count and the time limit go on.

        What the thesis code's vec env does when success ends every agent's episode
        (`common/vec_env/dummy_vec_env.py:51-54`) while its fixed window of 20 global
        steps continues; with `success_terminal` callers call it after a terminal step.
        """
        if self._t is None:
            raise RuntimeError("call reset() before reset_world()")
        raw = self._raw
        raw.scenario.reset_world(raw.world, raw.np_random)
        _resize_for_task(self.task, raw.world, self.landmark_size)
        self._world_ended = False
        return [self._shape(i, raw.observe(a.name)) for i, a in enumerate(self.spec.agents)]

    def step(self, actions: Sequence[np.ndarray]) -> StepResult:
        """Apply one thesis-layout action per agent (spec order, each of shape (act_dim,))
        and score the new state."""
        if len(actions) != self.spec.n_agents:
            raise ValueError(f"expected {self.spec.n_agents} actions, got {len(actions)}")
        for agent, act in zip(self.spec.agents, actions, strict=True):
            if np.shape(act) != (agent.act_dim,):
                raise ValueError(
                    f"{agent.name}: action has shape {np.shape(act)}, expected ({agent.act_dim},)"
                )
        res = self.step_joint(np.concatenate([np.asarray(a, np.float32) for a in actions]))
        return StepResult(
            obs=[o.copy() for o in np.split(res.obs, self._obs_split)],
            reward=res.reward,
            success=res.success,
            collisions=res.collisions,
            truncated=res.truncated,
            terminated=res.terminated,
        )

    def step_joint(self, action: np.ndarray) -> JointStep:
        """`step` for the joint action x = a_1 || ... || a_N, giving the joint observation.

        What collection and evaluation call at every step: no per-agent split and join.
        """
        if self._t is None:
            raise RuntimeError("call reset() before step()")
        if self._t >= self.spec.episode_len:
            raise RuntimeError("episode is over (time limit); call reset()")
        if self._world_ended:
            raise RuntimeError("success ended this world (success_terminal); call reset_world()")
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        if a.shape[0] != self._act_total:
            raise ValueError(f"joint action has {a.shape[0]} values, expected {self._act_total}")
        if not np.isfinite(a).all():
            bad = [
                ag.name
                for ag, part in zip(self.spec.agents, self._split_act(a))
                if not np.isfinite(part).all()
            ]
            raise ValueError(f"non-finite action of {', '.join(bad)}: {a}")
        a = np.minimum(np.maximum(a, self._low), self._high)
        if self.direct:
            obs, mpe_terminated, mpe_ended = self._step_direct(a)
            mpe_reward = None
        else:
            mpe_actions = {
                ag.name: to_mpe_action(ag, part)
                for ag, part in zip(self.spec.agents, self._split_act(a), strict=True)
            }
            obs_d, rewards, terminations, truncations, _ = self._env.step(mpe_actions)
            mpe_terminated, mpe_ended = any(terminations.values()), any(truncations.values())
            obs = np.concatenate(
                [self._shape(i, obs_d[ag.name]) for i, ag in enumerate(self.spec.agents)]
            )
            mpe_reward = float(np.mean([rewards[ag.name] for ag in self.spec.agents]))
        self._t += 1
        reward, success, collisions = self.evaluate()
        if self.reward_kind == "dense" and mpe_reward is not None:
            reward = mpe_reward  # mpe2's own numbers, straight from the env
        truncated = self._t >= self.spec.episode_len
        if mpe_terminated or mpe_ended != truncated:
            raise RuntimeError("mpe2 ended the episode at an unexpected step")
        terminated = self.success_terminal and success
        self._world_ended = terminated and not truncated
        return JointStep(obs, reward, success, collisions, truncated, terminated)

    def _split_act(self, a: np.ndarray) -> list[np.ndarray]:
        return np.split(a, self._act_split)

    def _step_direct(self, a: np.ndarray) -> tuple[np.ndarray, bool, bool]:
        """mpe2's SimpleEnv.step for a whole cycle of agents, without the AEC layers.

        The actions are set as mpe2's `_set_action` sets continuous ones (movement as
        the difference of a pair times the sensitivity, which for our pairs is the
        movement itself, message as given) and the world steps with mpe2's own physics
        and observations. mpe2's per-agent rewards, which its step computes every time,
        are computed only for the dense reward (`_dense_reward`, the same formula).
        """
        raw = self._raw
        world = raw.world
        dim_p, dim_c = world.dim_p, world.dim_c
        for agent, (lo, hi), n_move in zip(world.agents, self._act_slices, self._move_dims):
            u = np.zeros(dim_p)
            if agent.movable:
                u += a[lo : lo + n_move]
                u *= 5.0 if agent.accel is None else agent.accel
            agent.action.u = u
            agent.action.c = np.zeros(dim_c) if agent.silent else a[lo + n_move : hi].copy()
        world.step()
        raw.steps += 1
        ended = raw.steps >= raw.max_cycles
        terminated = not ended and bool(raw.scenario.is_terminal(world))
        observation = raw.scenario.observation
        if not self._reshaped:
            obs = np.empty(self._obs_total, np.float32)
            for agent, (lo, hi) in zip(world.agents, self._obs_slices):
                obs[lo:hi] = observation(agent, world)
        else:  # the padding stays zero
            obs = np.zeros(self._obs_total, np.float32)
            for agent, (lo, _), keep in zip(world.agents, self._obs_slices, self._keep):
                obs[lo : lo + keep] = observation(agent, world)[:keep]
        return obs, terminated, ended

    def evaluate(self) -> tuple[float, bool, int]:
        """(reward, success, collisions) of the current world state, for the chosen reward."""
        world = self._raw.world
        if self.task == "spread":
            sparse, success = _sparse_spread(world, self._landmark_cover)
        else:
            sparse, success = _SPARSE[self.task](world)
        collisions = count_collisions(world)
        if self.reward_kind == "sparse":
            reward = sparse
        elif self.reward_kind == "sparse_offset":
            reward = sparse + SPARSE_OFFSET
        else:  # mpe2's formula (the public-API path takes mpe2's own numbers)
            reward = self._dense_reward()
        return float(reward), success, collisions

    def _dense_reward(self) -> float:
        """mpe2's per-agent reward of the current state (same formula as its step), averaged."""
        raw, world = self._raw, self._raw.world
        local_ratio = raw.local_ratio
        global_reward = float(raw.scenario.global_reward(world)) if local_ratio is not None else 0.0
        per_agent = []
        for agent in world.agents:
            r = float(raw.scenario.reward(agent, world))
            if local_ratio is not None:
                r = global_reward * (1 - local_ratio) + r * local_ratio
            per_agent.append(r)
        return float(np.mean(per_agent))

    def close(self) -> None:
        """Release the env (mpe2 holds a pygame surface)."""
        self._env.close()


def make_task(
    task: str,
    agents: int = 2,
    reward: str = "sparse",
    episode_len: int = 20,
    seed: int | None = None,
    direct: bool = True,
    **options: Any,
) -> TaskEnv:
    """Build a TaskEnv; `agents` sizes spread only (simple has 1 agent, speaker_listener 2).

    `options` are TaskEnv's keyword options (success_terminal, cover, landmark_size,
    pad_obs, comm_obs, integrator). A `package.module:factory` task is built by
    shared/envs/custom_task.py instead, from its `task_kwargs`, `success_key` and
    `success_terminal` options (the env's own reward: `reward` is not used)."""
    if is_custom(task):
        from shared.envs.custom_task import CustomTaskEnv

        # (a TaskEnv by interface, not by class: what every caller uses of one)
        return CustomTaskEnv(  # type: ignore[return-value]
            task,
            options.get("task_kwargs"),
            episode_len,
            options.get("success_key"),
            seed=seed,
            success_terminal=bool(options.get("success_terminal", False)),
        )
    return TaskEnv(
        task,
        agents=agents,
        reward=reward,
        episode_len=episode_len,
        seed=seed,
        direct=direct,
        **options,
    )


class TaskConfig(Protocol):
    """What the task adapters read from a run config (a `shared.config.TrainConfig`, or
    anything with these attributes): this module stays free of the config's imports."""

    @property
    def task(self) -> str: ...
    @property
    def agents(self) -> int: ...
    @property
    def reward(self) -> str: ...
    @property
    def episode_len(self) -> int: ...
    @property
    def success_terminal(self) -> bool: ...
    @property
    def cover(self) -> str: ...
    @property
    def landmark_size(self) -> float | None: ...
    @property
    def pad_obs(self) -> bool: ...
    @property
    def comm_obs(self) -> bool: ...
    @property
    def integrator(self) -> str: ...
    @property
    def task_kwargs(self) -> dict[str, Any] | None: ...
    @property
    def success_key(self) -> str | None: ...


def is_custom(task: str) -> bool:
    """Whether `task` names a `package.module:factory` (shared/envs/custom_task.py) rather
    than one of TASKS."""
    return ":" in task


def task_options(cfg: TaskConfig) -> dict[str, Any]:
    """The config's task-level options, as `make_task` takes them."""
    if is_custom(cfg.task):
        return {
            "task_kwargs": cfg.task_kwargs,
            "success_key": cfg.success_key,
            "success_terminal": cfg.success_terminal,
        }
    return {
        "success_terminal": cfg.success_terminal,
        "cover": cfg.cover,
        "landmark_size": cfg.landmark_size,
        "pad_obs": cfg.pad_obs,
        "comm_obs": cfg.comm_obs,
        "integrator": cfg.integrator,
    }


def make_task_for(cfg: TaskConfig, seed: int | None = None, direct: bool = True) -> TaskEnv:
    """The run's environment, with every task option of its config: the trainer, the
    actors and the evaluators build theirs here, so they all step the same task."""
    return make_task(
        cfg.task, cfg.agents, cfg.reward, cfg.episode_len, seed, direct, **task_options(cfg)
    )


def task_spec_for(cfg: TaskConfig) -> TaskSpec:
    """The run's shapes (the learner and the counter size networks, buffers and SimHash
    projections from it): equal to `make_task_for(cfg).spec`. A custom task's is built
    and checked once per process (one env, reset and stepped once)."""
    if is_custom(cfg.task):
        from shared.envs.custom_task import custom_task_spec

        return custom_task_spec(cfg.task, cfg.task_kwargs, cfg.episode_len, cfg.success_key)
    return task_spec(
        cfg.task, cfg.agents, cfg.episode_len, pad_obs=cfg.pad_obs, comm_obs=cfg.comm_obs
    )
