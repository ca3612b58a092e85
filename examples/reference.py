"""mpe2's simple_reference with continuous actions and a success key, as a custom task.

`task: examples.reference:parallel_env` (run from the repository root, or with the
repository on PYTHONPATH on every host of a cluster). In simple_reference each of two
agents must bring the *other* agent to a landmark only it knows, by talking; mpe2 gives
no success signal, so this wrapper adds one to every agent's info: `at_goal` is true
when each agent's partner covers that agent's goal landmark (centres closer than the
sum of their radii), the condition mpe2's reward -|p_partner - p_goal|^2 pulls towards.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from mpe2 import simple_reference_v3
from pettingzoo.utils import BaseParallelWrapper

SUCCESS_KEY = "at_goal"


def at_goal(world: Any) -> bool:
    """Every agent's partner (goal_a) covers that agent's goal landmark (goal_b)."""
    for agent in world.agents:
        partner, landmark = agent.goal_a, agent.goal_b
        dist = float(np.linalg.norm(partner.state.p_pos - landmark.state.p_pos))
        if not dist < partner.size + landmark.size:
            return False
    return True


class SuccessInfo(BaseParallelWrapper):
    """Adds `at_goal` to every agent's info after each step."""

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        obs, rewards, terminations, truncations, infos = self.env.step(actions)
        ok = at_goal(self.env.unwrapped.world)
        infos = {name: {**infos.get(name, {}), SUCCESS_KEY: ok} for name in obs}
        return obs, rewards, terminations, truncations, infos


def parallel_env(max_cycles: int = 25, **kwargs: Any) -> SuccessInfo:
    """simple_reference_v3 with continuous actions (2 agents, observation 21, action 15:
    5 movement values and a 10-value message, each in [0, 1])."""
    return SuccessInfo(
        simple_reference_v3.parallel_env(max_cycles=max_cycles, continuous_actions=True, **kwargs)
    )
