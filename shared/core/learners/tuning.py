"""How many threads the batched update uses, chosen from measured update times.

No fixed choice is right on a machine shared with other processes: two threads beat one
when the second core is free and lose, badly for torch's spinning OpenMP threads, when
it is not (docs/performance.md, "Learner design and its measurements"). `TunedMADDPG`
wraps a `BatchedMADDPG` and lets a `LaneTuner` pick, block by block of updates, one of
`AUTO_MODES`, so the learner itself stays one way of computing the update and the caller
only says, through `contended`, when it knows other work runs beside the update (the
cluster's learner: while the evaluator evaluates weights it sent). Those updates get a
tuner of their own, so their stalls do not spoil the choice for the rest. The modes
differ only in the order of floating-point additions: reruns are equal up to rounding,
not bit for bit. A bf16 learner is tuned the same way: its modes only take other times.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from shared.core.learners.batched import BatchedMADDPG
from shared.core.learners.lanes import LaneTuner

# What the tuner chooses among, as (lanes, torch intra-op threads).
AUTO_MODES = ((1, 1), (2, 1), (1, 2))


class TunedMADDPG:
    """A `BatchedMADDPG` whose every update runs in the mode a tuner picks (`Learner`).

    Before each update it asks `contended()` (if given) which tuner to use, sets the
    chosen lanes and torch threads, and records the update's time into that tuner. The
    learner must have as many lanes as the most any mode uses (2 for `AUTO_MODES`).
    `torch.set_num_threads` is the wrapper's from then on.
    """

    def __init__(
        self,
        learner: BatchedMADDPG,
        contended: Callable[[], bool] | None = None,
        modes: Sequence[tuple[int, int]] = AUTO_MODES,
    ) -> None:
        if any(lanes not in (1, learner.lanes.n) for lanes, _ in modes):
            raise ValueError(
                f"each mode must run on 1 lane or all {learner.lanes.n} of the learner's, "
                f"got modes {list(modes)}"
            )
        self.learner = learner
        self.contended = contended
        self.tuner: LaneTuner[tuple[int, int]] = LaneTuner(modes)
        self.contended_tuner: LaneTuner[tuple[int, int]] = LaneTuner(modes)
        self.contended_updates = 0

    @property
    def updates(self) -> int:
        return self.learner.updates

    def update(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        next_obs: np.ndarray,
        done: np.ndarray,
    ) -> Mapping[str, float]:
        """The learner's update in the mode the (ordinary or contended) tuner picks."""
        contended = self.contended is not None and self.contended()
        self.contended_updates += contended
        tuner = self.contended_tuner if contended else self.tuner
        t0 = time.perf_counter()
        lanes, threads = tuner.choose()
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
        out = self.learner.update_on(lanes, obs, act, rew, next_obs, done)
        tuner.record(time.perf_counter() - t0)
        return out

    def stats(self) -> dict[str, float]:
        """The ordinary tuner's current mode, the tuners' picks and measured times
        (`lanesAxB_*` for ordinary updates, `contended_lanesAxB_*` for contended ones),
        `contended_share` the share of updates that were contended and
        `contended_updates` their number; `bf16` and `fused` as the learner reports them."""
        lanes, threads = self.tuner.current
        out = {"lanes": float(lanes), "threads": float(threads)}
        out["bf16"] = float(self.learner.precision == "bf16")
        out["fused"] = self.learner.stats()["fused"]
        quiet = sum(self.tuner.chosen.values())
        contended = sum(self.contended_tuner.chosen.values())
        out["contended_share"] = contended / max(1, quiet + contended)
        out["contended_updates"] = self.contended_updates
        for prefix, tuner in (("", self.tuner), ("contended_", self.contended_tuner)):
            total = max(1, sum(tuner.chosen.values()))
            for mode in tuner.options:
                name = f"{prefix}lanes{mode[0]}x{mode[1]}"  # lanes x torch threads
                out[f"{name}_share"] = tuner.chosen[mode] / total
                typical = tuner.estimate_s[mode]  # smoothed median update time
                out[f"{name}_update_ms"] = 1e3 * typical if typical is not None else 0.0
        return out

    # The rest is the learner's own.
    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.learner.act(obs)

    def actor_weights(self) -> list[dict[str, torch.Tensor]]:
        return self.learner.actor_weights()

    def load_actor_weights(self, weights: Sequence[dict[str, Any]]) -> None:
        self.learner.load_actor_weights(weights)

    def state_dict(self) -> dict:
        return self.learner.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.learner.load_state_dict(state)
