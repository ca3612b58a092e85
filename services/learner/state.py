"""What the learner service holds for a run it serves (`LearnerRun`), and `new_run`,
which builds it from a run's config and assignment.

A run's state is split by owner: `Intake` (intake.py: replay, what was taken and
counted, the episode boundaries, the log), `Sampling` (updates.py: the sampler, the
minibatches awaiting prices, the bonuses learnt from), `Outgoing` (outbound.py: the
publishers, the weights version, the credit window) and `Cuts` (checkpoint.py). Each
module is the one writer of its part; the others read it or call its methods.
`LearnerRun` holds the parts and what the run is (config, actors, learner, bonus
client). The runs served are a `RunGroup`: a run alone is a group of one (its learner
a `SoloRuns`), a lockstep group's runs share one `GroupMADDPG`; each run reads its
share of the group's learner through a `MemberLearner`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from services.learner.bonus import BonusClient
from services.learner.checkpoint import Cuts
from services.learner.evaluations import EvaluationsInFlight
from services.learner.intake import Intake
from services.learner.lockstep import Asks
from services.learner.outbound import Outgoing
from services.learner.updates import Sampling
from shared.config import TrainConfig, actors_error
from shared.core.learners import Learner
from shared.core.learners.runs import RunsLearner
from shared.envs.tasks import TaskSpec
from shared.net.protocol import episode_share
from shared.run.factories import minibatches_per_update
from shared.run.rollout import derive_seed

# Phases of the learner's wall time that stats() reports per update; the bonus wait is
# BonusClient.wait_s, and what none of them covers (waiting for messages, acks, stats,
# and the wait for the first `learning_starts` transitions) is reported as "other".
TIME_PHASES = ("sample", "update", "publish", "inbound")


class PhaseTimes:
    """Wall time by phase (s): where the learner's time per update goes. Each part adds
    its own phase (updates.py sample and update, outbound.py publish, main.py inbound)."""

    def __init__(self) -> None:
        self.spent = dict.fromkeys(TIME_PHASES, 0.0)

    def add(self, phase: str, seconds: float) -> None:
        self.spent[phase] += seconds


@dataclass
class RunGroup:
    """The runs a learner serves as one (run r of `runs` is member r): a run alone, a
    group of one, or a lockstep group's runs; one learner for all of them and, in
    lockstep, their one actor's requests."""

    runs: list[str]
    learner: RunsLearner
    grouped: bool = False  # a group's runs (`Assignment.group`), not a run alone
    asks: Asks | None = None  # lockstep
    # Runs of the group their `early_stop` rule ended while the others go on: member r
    # -> its fixed update arrays (`fixed_update_arrays`; its stack entry runs on them).
    retired: dict[int, tuple[np.ndarray, ...]] = field(default_factory=dict)

    @property
    def subs(self) -> str:
        """What the group's own subscriptions (the act requests, on the lead run's keys)
        are held under: they outlive the lead run when its rule ends it first."""
        return f"group:{self.runs[0]}"


class MemberLearner:
    """Run r's view of its group's learner: what the service reads and writes per run
    (the update and the acting are the group's, one call for every run)."""

    def __init__(self, group: RunsLearner, r: int) -> None:
        self.group, self.r = group, r

    @property
    def updates(self) -> int:
        return self.group.updates

    def actor_weights(self) -> list[dict[str, torch.Tensor]]:
        return self.group.run_actor_weights(self.r)

    def state_dict(self) -> dict:
        return self.group.run_state_dict(self.r)

    def stats(self) -> dict[str, float]:
        return self.group.stats()


@dataclass
class LearnerRun:
    """A run the learner serves: what it is, and its parts (each written by its module)."""

    run: str
    config: TrainConfig
    spec: TaskSpec
    actors: list[str]
    counter: str | None
    learner: Learner | MemberLearner
    bonus: BonusClient
    evaluations: EvaluationsInFlight
    intake: Intake
    sampling: Sampling
    outgoing: Outgoing
    cuts: Cuts = field(default_factory=Cuts)
    final: dict[str, int] = field(default_factory=dict)  # actor -> transitions it published
    time: PhaseTimes = field(default_factory=PhaseTimes)
    stopped: tuple[int, str] | None = None  # `early_stop`: the point it held at, and why
    best: float = -1.0  # `early_stop`: the best success so far (its point is in best.pt)

    @property
    def counting(self) -> bool:
        return self.config.counts

    @property
    def lockstep(self) -> bool:
        """interleave lockstep: actions are computed here, per step."""
        return self.config.interleave == "lockstep"

    @property
    def owed_total(self) -> int:
        """Updates the replay ratio asks for so far: one per transition after the warm-up."""
        return max(0, self.intake.ingested - self.config.learning_starts)

    @property
    def done(self) -> bool:
        """Every actor's share of the episodes is in replay and learnt, every weight and
        evaluation point out: the run can complete. (Whether or not an actor's
        "completed" came: a learner resumed after it may never see it.)"""
        return (
            (self.intake.all_in() or self.stopped is not None)
            and not self.intake.boundaries
            and self.learner.updates >= self.owed_total
            and not self.evaluations.unreported  # every point's row is out (or sent again)
        )


def open_error(config: TrainConfig, actors: int) -> str | None:
    """Why the cluster's learner cannot serve this run with this many actors, if so."""
    if config.bonus_at == "collection":
        return (
            "bonus_at collection: the cluster prices bonuses when it samples; run this "
            "config with macb train or as a run group (macb run/reproduce --local)"
        )
    if config.early_stop is not None and config.interleave != "lockstep":
        return (
            "early_stop: the cluster stops a run by its rule in lockstep (it holds each "
            "step after a point until the point's row is in); not interleave async: run "
            "it with macb train or as a run group (macb run/reproduce --local)"
        )
    return actors_error(config, actors)


def new_run(
    run: str,
    config: TrainConfig,
    spec: TaskSpec,
    actors: list[str],
    *,
    learner: Learner | MemberLearner,
    bonus: BonusClient,
    evaluations: EvaluationsInFlight,
    pubs: Mapping[str, Callable[[bytes], None]],
    counter: str | None = None,
    folder: Path | None = None,
    incarnation: str = "",
    grouped: bool = False,
    attempt: int | None = None,
) -> LearnerRun:
    """A run's state as it starts: an empty replay buffer (no larger than the run),
    the sampler seeded from the run's seed, nothing received, each actor's share of
    the episodes. `pubs` are the run's publishers: weights, eval, ack (a `grouped`
    run's actor acts by request: no weights go to it)."""
    shares = {
        a: episode_share(config.episodes, len(actors), r) * config.episode_len
        for r, a in enumerate(actors)
    }
    capacity = min(config.buffer_size, config.episodes * config.episode_len)
    return LearnerRun(
        run=run,
        config=config,
        spec=spec,
        actors=actors,
        counter=counter,
        learner=learner,
        bonus=bonus,
        evaluations=evaluations,
        intake=Intake.open(capacity, spec.joint_obs_dim, spec.joint_act_dim, shares),
        sampling=Sampling(
            rng=np.random.default_rng(derive_seed(config.seed, "sampler")),
            per_update=minibatches_per_update(config),
        ),
        outgoing=Outgoing(
            pubs["weights"],
            pubs["eval"],
            pubs["ack"],
            incarnation,
            to_actors=not grouped,
            attempt=attempt,
        ),
        cuts=Cuts(folder),
    )
