"""Your own task: any PettingZoo ParallelEnv named `package.module:factory`.

The built-in tasks (shared/envs/tasks.py) know mpe2's worlds; this adapter knows only the
PettingZoo parallel API, so a run config may name any factory that returns a
ParallelEnv with Box observation and action spaces. It gives the trainer, the actors,
the evaluator, the learner and the counter what a built-in task gives them (a
`TaskSpec`, `reset`, `step_joint`, `reset_world`, RNG state), so none of them has a
special case:

* actions: every agent's policy acts in [-1, 1]^d; the adapter scales each value to
  its Box's bounds (`low + (a + 1) / 2 * (high - low)`), so networks, noise and
  SimHash vectors look alike on every task;
* observations: each agent's Box, flattened, in `possible_agents` order;
* reward: the mean over agents of the env's rewards (a team reward, like `dense`);
* success: an optional info key (`success_key`): a step succeeds when some agent's
  info holds a true value under it; without a key the success rate stays 0;
* episodes last `episode_len` steps: the adapter owns the time limit. A step at which
  the env ends every agent earlier (termination, or its own shorter time limit) goes
  on in a fresh `env.reset()` inside the same episode: a termination is terminal
  (done = 1), an early truncation is not (`JointStep.restart`).

Bad factories, discrete or unbounded spaces and observations of the wrong shape are
refused with a `TaskError` naming the agent and the space, at config time (the config
builds one env and steps it once) and again when an env is built.
"""

from __future__ import annotations

import functools
import importlib
import json
import math
import os
import re
import sys
import types
from collections.abc import Sequence
from typing import Any

import numpy as np

from shared.core.joint import offsets
from shared.envs.spec import AgentSpec, JointStep, StepResult, TaskSpec

#: `package.module:factory` (the factory may be a dotted attribute path too).
SPEC_RE = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")


class TaskError(ValueError):
    """A custom task refused: the message names the factory, the agent and the space."""


def module_of(task: str) -> str:
    return task.split(":", 1)[0]


def load_factory(task: str) -> Any:
    """Import `package.module` and return its `factory` attribute, or say what failed.

    The attribute path (`factory`, or `Class.method`) stays in the named module: a part
    that is private (`_x`, dunders) or a module the named one imported is refused, so
    naming an allowed module cannot reach `os.system` or builtins through it."""
    if not SPEC_RE.match(task):
        raise TaskError(
            f"{task}: a custom task is `package.module:factory` (e.g. "
            "mpe2.simple_reference_v3:parallel_env)"
        )
    module_name, attr = task.split(":", 1)
    # Like `python -m` and uvicorn: a module in the working directory is found too (after
    # the installed packages), so `macb train` and the services started from a project
    # folder import the same file.
    cwd = os.getcwd()
    if cwd not in sys.path:
        sys.path.append(cwd)
    try:
        obj: Any = importlib.import_module(module_name)
    except Exception as err:  # the user's module may raise anything on import
        raise TaskError(
            f"{task}: cannot import {module_name}: {type(err).__name__}: {err}"
        ) from None
    for part in attr.split("."):
        if part.startswith("_"):
            raise TaskError(f"{task}: {part!r} is private; name a public factory of {module_name}")
        if not hasattr(obj, part):
            raise TaskError(f"{task}: {module_name} has no attribute {attr!r}")
        obj = getattr(obj, part)
        if isinstance(obj, types.ModuleType):
            raise TaskError(
                f"{task}: {part!r} is a module ({obj.__name__}); name a factory in its own "
                f"module: `{obj.__name__}:NAME`"
            )
    if not callable(obj):
        raise TaskError(f"{task}: {attr} is a {type(obj).__name__}, not a factory")
    return obj


def build_env(task: str, kwargs: dict[str, Any] | None) -> Any:
    """Call the factory with `kwargs` and check that it gave a PettingZoo ParallelEnv."""
    from pettingzoo import AECEnv, ParallelEnv

    factory = load_factory(task)
    try:
        env = factory(**(kwargs or {}))
    except Exception as err:
        raise TaskError(
            f"{task}: the factory raised {type(err).__name__}: {err} (task_kwargs {kwargs or {}})"
        ) from None
    if isinstance(env, AECEnv):
        raise TaskError(
            f"{task}: gave an AEC env ({type(env).__name__}); name a factory of the "
            "parallel API (mpe2 and PettingZoo modules: parallel_env)"
        )
    if not isinstance(env, ParallelEnv):
        raise TaskError(f"{task}: gave a {type(env).__name__}, not a PettingZoo ParallelEnv")
    if not list(getattr(env, "possible_agents", []) or []):
        raise TaskError(f"{task}: the env has no possible_agents")
    return env


def _agent_spec(task: str, env: Any, name: str) -> tuple[AgentSpec, np.ndarray, np.ndarray]:
    """One agent's spec in the [-1, 1] action layout, and its Box bounds (flattened)."""
    from gymnasium.spaces import Box

    obs_space, act_space = env.observation_space(name), env.action_space(name)
    if not isinstance(obs_space, Box):
        raise TaskError(
            f"{task}: agent {name}: observation space {obs_space} is not a Box "
            "(only Box observations can be hashed and fed to the networks)"
        )
    if not isinstance(act_space, Box):
        mpe2 = task.startswith("mpe2.") and "Discrete" in str(act_space)
        hint = " (mpe2: task_kwargs {continuous_actions: true})" if mpe2 else ""
        raise TaskError(
            f"{task}: agent {name}: action space {act_space} is not a Box: DDPG "
            f"and MADDPG need continuous actions{hint}"
        )
    low = np.asarray(act_space.low, np.float64).reshape(-1)
    high = np.asarray(act_space.high, np.float64).reshape(-1)
    if not (np.isfinite(low).all() and np.isfinite(high).all()) or not (high > low).all():
        raise TaskError(
            f"{task}: agent {name}: action space {act_space} needs finite bounds "
            "with high > low (actions are scaled from [-1, 1] to them)"
        )
    obs_dim = int(math.prod(obs_space.shape))
    act_dim = int(low.shape[0])
    if obs_dim < 1 or act_dim < 1:
        raise TaskError(f"{task}: agent {name}: empty space ({obs_space}, {act_space})")
    spec = AgentSpec(
        name=name,
        obs_dim=obs_dim,
        act_low=(-1.0,) * act_dim,
        act_high=(1.0,) * act_dim,
        obs_layout=f"obs({obs_dim}) of {obs_space}",
        act_layout=f"action({act_dim}) in [-1,1] scaled to {act_space}",
    )
    return spec, low, high


def _flat_obs(task: str, env: Any, name: str, obs: dict[str, Any], when: str) -> np.ndarray:
    """An agent's observation flattened, after checking it has its space's shape."""
    if name not in obs:
        raise TaskError(f"{task}: agent {name}: no observation after {when}")
    space = env.observation_space(name)
    o = np.asarray(obs[name], np.float32)
    if o.shape != tuple(space.shape):
        raise TaskError(
            f"{task}: agent {name}: observation of shape {o.shape} after {when}, "
            f"but its space is {space}"
        )
    return o.reshape(-1)


@functools.cache
def _checked_spec(
    task: str, kwargs_json: str, episode_len: int, success_key: str | None
) -> TaskSpec:
    """Build one env, reset and step it once with mid-range actions, and check every
    agent's spaces, observations and (with `success_key`) the info key."""
    env = CustomTaskEnv(task, json.loads(kwargs_json), episode_len, success_key)
    try:
        env.reset(seed=0)
        res = env.step_joint(np.zeros(env.spec.joint_act_dim, np.float32))
        if success_key is not None and not env.seen_success_key:
            raise TaskError(
                f"success_key: {success_key!r} is in no agent's info after a step of "
                f"{task} (info keys: {', '.join(sorted(env.info_keys)) or 'none'})"
            )
        del res
        return env.spec
    finally:
        env.close()


def custom_task_spec(
    task: str, kwargs: dict[str, Any] | None, episode_len: int, success_key: str | None
) -> TaskSpec:
    """The task's shapes, checked once per process (cached by its arguments)."""
    return _checked_spec(task, json.dumps(kwargs or {}, sort_keys=True), episode_len, success_key)


class CustomTaskEnv:
    """A PettingZoo ParallelEnv behind the interface of `shared.envs.tasks.TaskEnv`."""

    def __init__(
        self,
        task: str,
        kwargs: dict[str, Any] | None = None,
        episode_len: int = 20,
        success_key: str | None = None,
        seed: int | None = None,
        success_terminal: bool = False,
    ) -> None:
        if episode_len < 1:
            raise TaskError(f"episode_len must be >= 1, got {episode_len}")
        self.task = task
        self._env = build_env(task, kwargs)
        agents: list[AgentSpec] = []
        lows, highs = [], []
        for name in self._env.possible_agents:
            spec, low, high = _agent_spec(task, self._env, name)
            agents.append(spec)
            lows.append(low)
            highs.append(high)
        self.spec = TaskSpec(name=task, agents=tuple(agents), episode_len=episode_len)
        self.success_key = success_key
        self.success_terminal = success_terminal
        self._names = [a.name for a in agents]
        self._act_off = offsets(self.spec.act_dims)
        self._obs_split = offsets(self.spec.obs_dims)[1:-1]
        self._low = [lo.astype(np.float32) for lo in lows]
        self._half = [((hi - lo) / 2).astype(np.float32) for lo, hi in zip(lows, highs)]
        self._act_shape = [self._env.action_space(n).shape for n in self._names]
        self._act_dtype = [self._env.action_space(n).dtype for n in self._names]
        self._pending_seed = seed
        self._t: int | None = None
        self._world_ended = False
        self.seen_success_key = False  # whether any info held `success_key` (checks)
        self.info_keys: set[str] = set()

    # ------------------------------------------------------------------ episodes
    def _joint(self, obs: dict[str, Any], when: str) -> np.ndarray:
        return np.concatenate([_flat_obs(self.task, self._env, n, obs, when) for n in self._names])

    def _reset_env(self, seed: int | None, when: str) -> np.ndarray:
        obs, _ = self._env.reset(seed=seed)
        missing = [n for n in self._names if n not in self._env.agents]
        if missing:
            raise TaskError(f"{self.task}: agents {missing} are not alive after {when}")
        return self._joint(obs, when)

    def reset(self, seed: int | None = None) -> list[np.ndarray]:
        """Start an episode; a seed reseeds the env, no seed continues it."""
        if seed is None:
            seed, self._pending_seed = self._pending_seed, None
        else:
            self._pending_seed = None
        joint = self._reset_env(seed, "reset")
        self._t = 0
        self._world_ended = False
        return [o.copy() for o in np.split(joint, self._obs_split)]

    def reset_world(self) -> list[np.ndarray]:
        """A fresh `env.reset()` (its RNG continuing) inside the running episode, after
        the env ended early or a success was terminal; the step count goes on."""
        if self._t is None:
            raise RuntimeError("call reset() before reset_world()")
        joint = self._reset_env(None, "reset")
        self._world_ended = False
        return [o.copy() for o in np.split(joint, self._obs_split)]

    def env_action(self, i: int, a: np.ndarray) -> np.ndarray:
        """Agent i's action in [-1, 1] scaled to its Box (shape and dtype of the space)."""
        scaled = self._low[i] + (np.clip(a, -1.0, 1.0) + 1.0) * self._half[i]
        return scaled.reshape(self._act_shape[i]).astype(self._act_dtype[i], copy=False)

    def step_joint(self, action: np.ndarray) -> JointStep:
        """One step of every agent from the joint action x = a_1 || ... || a_N."""
        if self._t is None:
            raise RuntimeError("call reset() before step()")
        if self._t >= self.spec.episode_len:
            raise RuntimeError("episode is over (time limit); call reset()")
        if self._world_ended:
            raise RuntimeError("the env ended this world; call reset_world()")
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        if a.shape[0] != self.spec.joint_act_dim:
            raise ValueError(
                f"joint action has {a.shape[0]} values, expected {self.spec.joint_act_dim}"
            )
        if not np.isfinite(a).all():
            raise ValueError(f"non-finite action: {a}")
        off = self._act_off
        actions = {n: self.env_action(i, a[off[i] : off[i + 1]]) for i, n in enumerate(self._names)}
        obs_d, rew_d, term_d, trunc_d, info_d = self._env.step(actions)
        obs = self._joint(obs_d, "a step")
        reward = float(np.mean([float(rew_d.get(n, 0.0)) for n in self._names]))
        success = False
        for n in self._names:
            info = info_d.get(n) or {}
            self.info_keys.update(str(k) for k in info)
            if self.success_key is not None and self.success_key in info:
                self.seen_success_key = True
                success = success or bool(info[self.success_key])
        self._t += 1
        truncated = self._t >= self.spec.episode_len
        env_term = any(bool(term_d.get(n, False)) for n in self._names)
        env_trunc = any(bool(trunc_d.get(n, False)) for n in self._names)
        terminated = env_term or (self.success_terminal and success)
        # Agents the env dropped (it ended them) also end this world for the rest.
        ended = env_term or env_trunc or len(self._env.agents) < len(self._names)
        restart = ended and not terminated and not truncated
        self._world_ended = (terminated or restart) and not truncated
        return JointStep(obs, reward, success, 0, truncated, terminated, restart)

    def step(self, actions: Sequence[np.ndarray]) -> StepResult:
        """`step_joint` with one action per agent (spec order)."""
        if len(actions) != self.spec.n_agents:
            raise ValueError(f"expected {self.spec.n_agents} actions, got {len(actions)}")
        res = self.step_joint(np.concatenate([np.asarray(x, np.float32) for x in actions]))
        return StepResult(
            obs=[o.copy() for o in np.split(res.obs, self._obs_split)],
            reward=res.reward,
            success=res.success,
            collisions=res.collisions,
            truncated=res.truncated,
            terminated=res.terminated,
            restart=res.restart,
        )

    # ------------------------------------------------------------------ RNG state
    def _rng(self) -> np.random.Generator | None:
        rng = getattr(self._env.unwrapped, "np_random", None)
        return rng if isinstance(rng, np.random.Generator) else None

    def rng_state(self) -> dict[str, Any] | None:
        """The env's numpy RNG state, if it exposes one (`unwrapped.np_random`, as
        PettingZoo envs do), for `macb train --resume`; None if it has none."""
        if self._pending_seed is not None:
            raise RuntimeError("reset the env once before saving its RNG state")
        rng = self._rng()
        return None if rng is None else dict(rng.bit_generator.state)

    def set_rng_state(self, state: dict[str, Any] | None) -> None:
        rng = self._rng()
        if state is None or rng is None:
            raise TaskError(
                f"{self.task}: its env exposes no numpy np_random, so a resumed run "
                "cannot draw the episodes it would have drawn; start the run again"
            )
        self._pending_seed = None
        rng.bit_generator.state = state

    def close(self) -> None:
        self._env.close()
