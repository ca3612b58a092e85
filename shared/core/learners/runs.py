"""What a trainer needs of R runs' learners, and a lone learner as a group of one.

The one-process trainer (cli/trainer.py) trains R >= 1 runs through one loop; it holds
their learners only through `RunsLearner`, whose arrays carry a leading run axis. A
group of R >= 2 runs is one `GroupMADDPG` (group.py); a run alone keeps the learner its
config asks for (the reference `MADDPG`, a `BatchedMADDPG` with its lanes, or a
`TunedMADDPG`), wrapped by `SoloRuns`, which adds and drops the run axis and nothing
else: the learner computes what it computes without the wrapper, bit for bit.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from shared.core.learners.base import Learner


@runtime_checkable
class RunsLearner(Protocol):
    """R runs' learners behind one interface: `act` and `update` take arrays whose first
    axis is the run (run r's batch at index r, as `Learner.update` takes it alone), the
    state and the actors are per run, in a lone learner's formats."""

    @property
    def runs(self) -> int:
        """R, the length of every array's run axis."""
        ...

    @property
    def updates(self) -> int:
        """Updates done so far (every run's: the runs update together)."""
        ...

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic joint actions of every run: (R, ..., joint_obs) -> (R, ..., joint_act)."""
        ...

    def update(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        next_obs: np.ndarray,
        done: np.ndarray,
    ) -> Mapping[str, float]:
        """One update of every run, run r's from its own batch (index r of each array)."""
        ...

    def stats(self) -> dict[str, float]:
        """How the update runs (`Learner.stats`), for the provenance and the metrics."""
        ...

    def run_state_dict(self, run: int) -> dict:
        """Run `run`'s checkpoint in the reference's format (`Learner.state_dict`)."""
        ...

    def load_run_state_dicts(self, states: Sequence[dict]) -> None:
        """Every run's checkpoint at once (one per run, at the same update)."""
        ...

    def run_learner(self, run: int) -> Learner:
        """Run `run`'s learner alone (for its final checkpoint)."""
        ...

    def run_actor_weights(self, run: int) -> list[dict[str, torch.Tensor]]:
        """Run `run`'s actors in `Learner.actor_weights`' format."""
        ...

    def load_run_actor_weights(self, run: int, weights: Sequence[dict[str, Any]]) -> None: ...

    def weights_changed(self) -> None:
        """Call after writing weights other than through `update` or the loads above."""
        ...


class SoloRuns:
    """One `Learner` as a group of one run (`RunsLearner`): the run axis of length 1 is
    dropped on the way in and added on the way out; everything else is the learner's."""

    runs = 1

    def __init__(self, learner: Learner) -> None:
        self.learner = learner

    @property
    def updates(self) -> int:
        return self.learner.updates

    def act(self, obs: np.ndarray) -> np.ndarray:
        self._check(obs)
        return self.learner.act(obs[0])[None]

    def update(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        next_obs: np.ndarray,
        done: np.ndarray,
    ) -> Mapping[str, float]:
        self._check(obs)
        return self.learner.update(obs[0], act[0], rew[0], next_obs[0], done[0])

    def stats(self) -> dict[str, float]:
        return self.learner.stats()

    def run_state_dict(self, run: int) -> dict:
        return self.run_learner(run).state_dict()

    def load_run_state_dicts(self, states: Sequence[dict]) -> None:
        if len(states) != 1:
            raise ValueError(f"{len(states)} states for a group of 1 run")
        self.learner.load_state_dict(states[0])

    def run_learner(self, run: int) -> Learner:
        if run != 0:
            raise IndexError(f"run {run} of a group of 1 run")
        return self.learner

    def run_actor_weights(self, run: int) -> list[dict[str, torch.Tensor]]:
        return self.run_learner(run).actor_weights()

    def load_run_actor_weights(self, run: int, weights: Sequence[dict[str, Any]]) -> None:
        self.run_learner(run).load_actor_weights(weights)

    def weights_changed(self) -> None:
        """The learner's loads mark its own weight copies stale; nothing else to do."""
        changed = getattr(self.learner, "weights_changed", None)
        if changed is not None:
            changed()

    @staticmethod
    def _check(obs: np.ndarray) -> None:
        if len(obs) != 1:
            raise ValueError(f"obs has {len(obs)} runs, the group 1")
