"""Small PettingZoo ParallelEnvs for the custom-task tests (`task: tests.custom_envs:tiny`).

`tiny(...)` builds a real ParallelEnv whose spaces, early ends and success info the
task_kwargs choose, and which records the actions it was given, so a test can check
what the adapter sends and refuses. Observations are each agent's position, moved by
its first action value each step.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.spaces import Box, Discrete
from pettingzoo import ParallelEnv

NOT_A_FACTORY = 3


class TinyEnv(ParallelEnv):
    metadata = {"name": "tiny_v0"}

    def __init__(
        self,
        agents: int = 2,
        obs: str = "box",
        act: str = "box",
        low: float = -2.0,
        high: float = 4.0,
        act_shape: tuple[int, ...] = (2,),
        wrong_obs_shape: bool = False,
        terminate_at: int | None = None,
        truncate_at: int | None = None,
        success_at: int | None = None,
        nan_at: int | None = None,
    ) -> None:
        self.possible_agents = [f"a{i}" for i in range(agents)]
        self.agents = list(self.possible_agents)
        self.kind = (obs, act)
        self.low, self.high, self.act_shape = low, high, tuple(act_shape)
        self.wrong_obs_shape = wrong_obs_shape
        self.terminate_at, self.truncate_at, self.success_at = (
            terminate_at,
            truncate_at,
            success_at,
        )
        self.nan_at = nan_at  # the step of each episode whose reward is NaN (a bug's)
        self.np_random = np.random.default_rng()
        self.actions: list[dict[str, Any]] = []
        self.resets = 0
        self.t = 0
        self.pos = {a: np.zeros(3, np.float32) for a in self.possible_agents}

    def observation_space(self, agent: str) -> Any:
        return Discrete(4) if self.kind[0] == "discrete" else Box(-10, 10, (3,), np.float32)

    def action_space(self, agent: str) -> Any:
        if self.kind[1] == "discrete":
            return Discrete(5)
        if self.kind[1] == "unbounded":
            return Box(-np.inf, np.inf, self.act_shape, np.float32)
        return Box(self.low, self.high, self.act_shape, np.float32)

    def _obs(self) -> dict[str, np.ndarray]:
        if self.wrong_obs_shape:
            return {a: np.zeros(4, np.float32) for a in self.agents}
        return {a: self.pos[a].copy() for a in self.agents}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        self.agents = list(self.possible_agents)
        self.t = 0
        self.resets += 1
        self.pos = {
            a: self.np_random.uniform(-1, 1, 3).astype(np.float32) for a in self.possible_agents
        }
        return self._obs(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        self.actions.append(actions)
        self.t += 1
        for a in self.agents:
            self.pos[a][0] += 0.1 * float(np.asarray(actions[a]).reshape(-1)[0])
        obs = self._obs()
        rewards = {a: float(i + self.t) for i, a in enumerate(self.agents)}
        if self.t == self.nan_at:
            rewards = dict.fromkeys(self.agents, float("nan"))
        terms = {a: self.t == self.terminate_at for a in self.agents}
        truncs = {a: self.t == self.truncate_at for a in self.agents}
        infos = {a: {"hit": self.t == self.success_at} for a in self.agents}
        if any(terms.values()) or any(truncs.values()):
            self.agents = []
        return obs, rewards, terms, truncs, infos


def tiny(**kwargs: Any) -> TinyEnv:
    return TinyEnv(**kwargs)


def raises(**kwargs: Any) -> TinyEnv:
    raise RuntimeError("this factory always fails")


def gives_a_dict() -> dict:
    return {"not": "an env"}
