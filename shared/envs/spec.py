"""The shapes a task gives its callers: each agent's interface, the task's sizes and one
step's result. Their own module, so the built-in tasks (tasks.py) and custom
PettingZoo tasks (custom_task.py) both build them without importing each other."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class AgentSpec:
    """One agent's interface in the thesis layout, so learners never see mpe2's 5-vectors."""

    name: str
    obs_dim: int
    act_low: tuple[float, ...]
    act_high: tuple[float, ...]
    obs_layout: str
    act_layout: str

    @property
    def act_dim(self) -> int:
        """Action width in the thesis layout (2 for movement, 3 for the speaker's message)."""
        return len(self.act_low)

    @property
    def move_dim(self) -> int:
        """Leading movement dims (those with a negative lower bound); the rest is a message."""
        return sum(1 for low in self.act_low if low < 0.0)


@dataclass(frozen=True)
class TaskSpec:
    """Shapes of one task, enough to size networks, buffers and SimHash projections."""

    name: str
    agents: tuple[AgentSpec, ...]
    episode_len: int

    @property
    def n_agents(self) -> int:
        return len(self.agents)

    @property
    def obs_dims(self) -> tuple[int, ...]:
        return tuple(a.obs_dim for a in self.agents)

    @property
    def act_dims(self) -> tuple[int, ...]:
        return tuple(a.act_dim for a in self.agents)

    @property
    def joint_obs_dim(self) -> int:
        """Size of s = o_1 || ... || o_N (the centralized critic and Cen-MACB input)."""
        return sum(self.obs_dims)

    @property
    def joint_act_dim(self) -> int:
        """Size of x = a_1 || ... || a_N."""
        return sum(self.act_dims)


class JointStep(NamedTuple):
    """One joint step: the joint observation s' = o'_1 || ... || o'_N and the metrics.

    `terminated` is True only with `success_terminal`, at a step where success holds
    (or, in a custom task, where its env terminated): `obs` is then the terminal
    observation, and unless the time limit also ends the episode the caller continues
    it from `reset_world()`. `restart` (custom tasks only) says the env ended its own
    episode before `episode_len` without a terminal state: not terminal, but the caller
    continues from `reset_world()` all the same.
    """

    obs: np.ndarray
    reward: float
    success: bool
    collisions: int
    truncated: bool
    terminated: bool = False
    restart: bool = False


@dataclass
class StepResult:
    """What one joint step gives the actor: observations, the team reward and the metrics."""

    obs: list[np.ndarray]
    reward: float
    success: bool
    collisions: int
    truncated: bool
    terminated: bool = False
    restart: bool = False
