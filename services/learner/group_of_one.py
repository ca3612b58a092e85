"""A run alone's learner seen as a group of one, so the learner service has one path.

`GroupOfOne` wraps what `shared.run.factories.build_learner` makes for a run (MADDPG,
BatchedMADDPG, TunedMADDPG) and answers the calls the service makes of a group's
`GroupMADDPG` (the update and the acting for every run at once, a run's weights and
checkpoint by its place), for the one run: run 0's arrays are the run's own, passed
through unchanged, so a run alone computes what it did before. Kept small and private
to the learner service: a learner with these methods of its own can replace it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from shared.core.learners import Learner


class GroupOfOne:
    """`learner` as a group of one run."""

    runs = 1

    def __init__(self, learner: Learner) -> None:
        self.learner = learner

    @property
    def updates(self) -> int:
        return self.learner.updates

    def update(self, *cols: np.ndarray) -> dict[str, float]:
        """The group's columns, (1, ...) each: the run's own update."""
        return self.learner.update(*(c[0] for c in cols))

    def act(self, obs: np.ndarray) -> np.ndarray:
        """(1, ..., joint_obs) -> (1, ..., joint_act)."""
        return self.learner.act(obs[0])[None]

    def run_actor_weights(self, run: int) -> list[dict[str, torch.Tensor]]:
        return self.learner.actor_weights()

    def load_run_actor_weights(self, run: int, weights: Sequence[dict[str, Any]]) -> None:
        self.learner.load_actor_weights(weights)

    def run_state_dict(self, run: int) -> dict:
        return self.learner.state_dict()

    def load_run_state_dicts(self, states: Sequence[dict]) -> None:
        (state,) = states
        self.learner.load_state_dict(state)

    def stats(self) -> dict[str, float]:
        return self.learner.stats()
