"""The policies an evaluator acts with when its runs are in lockstep: the learner's own
`act` on the weights it sent, for a run alone or for a group's runs at once, so a point
is the one-process trainer's to the bit (JointPolicy's numpy forward, which the
evaluator uses otherwise, equals it only up to float32 rounding)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from shared.config import TrainConfig
from shared.envs.tasks import TaskSpec
from shared.run.factories import build_learner


class LearnerPolicy:
    """The learner's own `act` on the weights it sent: with `interleave: lockstep` the
    points are `macb train`'s to the bit, and it evaluates with this very function
    (JointPolicy's numpy forward equals it only up to float32 rounding)."""

    def __init__(self, config: TrainConfig, spec: TaskSpec) -> None:
        exact = config.model_copy(update={"learner_lanes": 1})  # acting: no lanes to tune
        self.learner = build_learner(exact, spec)

    def load(self, weights: list[dict[str, Any]]) -> None:
        self.learner.load_actor_weights(
            [{k: torch.as_tensor(np.array(v)) for k, v in sd.items()} for sd in weights]
        )

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.learner.act(obs)


class GroupPolicy:
    """A group's actors in one GroupMADDPG (acting only): each run's weights loaded as
    its points come, one `act` for every run's worlds (the learner's own function, so
    each run's actions are those of `LearnerPolicy` alone, to the bit)."""

    def __init__(self, configs: list[TrainConfig], spec: TaskSpec) -> None:
        from shared.core.learners.group import GroupMADDPG
        from shared.run.factories import agent_dims, learner_spec

        self.learner = GroupMADDPG(
            agent_dims(spec),
            [learner_spec(c) for c in configs],
            precision=configs[0].precision,
            device=configs[0].device,
        )

    def load(self, run: int, weights: list[dict[str, Any]]) -> None:
        self.learner.load_run_actor_weights(
            run, [{k: torch.as_tensor(np.array(v)) for k, v in sd.items()} for sd in weights]
        )

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.learner.act(obs)
