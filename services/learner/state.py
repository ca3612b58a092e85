"""What the learner service holds for a run it serves (`LearnerRun`: its `done` rule and
`run_stats`), and for a run group served in lockstep (`LockstepGroup`, each run reading
its share of the one `GroupMADDPG` through a `MemberLearner`); `new_run` builds a
run's state from its config and assignment."""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from services.learner.bonus import BonusClient
from services.learner.evaluations import EvaluationsInFlight
from shared.config import TrainConfig, actors_error
from shared.core.exploration import BonusDiagnostics
from shared.core.learners import Learner
from shared.core.learners.group import GroupMADDPG
from shared.core.replay import ReplayBuffer
from shared.envs.tasks import TaskSpec
from shared.net.messages import Transitions
from shared.net.protocol import AckTracker, ReceiveCursor, episode_share
from shared.persist.wal import WriteAheadLog
from shared.run.factories import minibatches_per_update
from shared.run.rollout import derive_seed

# Phases of the learner's wall time that stats() reports per update; the bonus wait is
# BonusClient.wait_s, and what none of them covers (waiting for messages, acks, stats,
# and the wait for the first `learning_starts` transitions) is reported as "other".
TIME_PHASES = ("sample", "update", "publish", "inbound")


class Boundary(NamedTuple):
    """An ingested episode's end: weights go out once `updates` updates are done."""

    episode: int
    updates: int
    env_steps: int
    collisions_cum: int


class MemberLearner:
    """Run r's view of its group's learner: what the service reads and writes per run
    (the update and the acting are the group's, one call for every run)."""

    def __init__(self, group: GroupMADDPG, r: int) -> None:
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
class LockstepGroup:
    """A run group served in lockstep: one learner for its runs (run r of `runs` is
    member r), one actor stepping their worlds, one act request per step for all."""

    runs: list[str]
    learner: GroupMADDPG
    actor: str
    action_pub: Callable[[bytes], None]
    wanted: tuple[int, np.ndarray] | None = None  # the open request: (seq, (R, obs))
    answered: tuple[int, bytes] | None = None  # the last answer, for a repeated request
    unpriced: list = field(default_factory=list)  # per run, minibatches awaiting prices


@dataclass
class LearnerRun:
    """Everything the learner holds for a run it serves."""

    run: str
    config: TrainConfig
    spec: TaskSpec
    learner: Learner | MemberLearner
    buffer: ReplayBuffer
    rng: np.random.Generator
    actors: list[str]
    counter: str | None
    bonus: BonusClient
    evaluations: EvaluationsInFlight
    weights_pub: Callable[[bytes], None]
    eval_pub: Callable[[bytes], None]
    ack_pub: Callable[[bytes], None]
    received: ReceiveCursor  # what has been taken from each actor (whole episodes only)
    counted: AckTracker  # how far the counter has acknowledged each actor
    held: dict[str, collections.deque[Transitions]]  # received, not yet counted
    final: dict[str, int] = field(default_factory=dict)  # actor -> transitions it published
    ingested: int = 0
    episodes: int = 0
    collisions_cum: int = 0
    boundaries: collections.deque[Boundary] = field(default_factory=collections.deque)
    version: int = 0
    lags: collections.deque[int] = field(default_factory=lambda: collections.deque(maxlen=200))
    window_open: bool = True
    last_ack: float = 0.0
    last_weights: float = 0.0  # when weights last went to the actors
    last_stats: float = 0.0
    last_ckpt: float = field(default_factory=time.monotonic)
    t0: float = field(default_factory=time.perf_counter)
    bonus_means: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100)
    )
    # Wall time by phase (s): where the learner's time per update goes.
    time: dict[str, float] = field(default_factory=lambda: dict.fromkeys(TIME_PHASES, 0.0))
    contended_updates: int = 0
    diagnostics: BonusDiagnostics = field(default_factory=BonusDiagnostics)
    minibatches_per_update: int = 1  # 1, or one per agent (`minibatch: per-agent`)
    log: WriteAheadLog | None = None  # every batch taken, before it is acknowledged
    folder: Path | None = None  # DATA_DIR/learner/RUN
    ingested_pos: dict[str, int] = field(default_factory=dict)  # per actor, in replay
    shares: dict[str, int] = field(default_factory=dict)  # transitions each actor owes
    incarnation: str = ""  # this process's weights are newer than any before a restart
    resumed_from: int | None = None  # the cut's episode, when resumed
    cuts: int = 0
    cut_s: float = 0.0  # wall time spent writing cuts (the log's fsync included)
    cut_bytes: int = 0  # size of the last cut file
    unpriced: list = field(default_factory=list)  # minibatches drawn, bonus query unanswered
    lockstep: bool = False  # interleave lockstep: actions are computed here, per step
    wanted: dict[str, tuple[int, np.ndarray]] = field(default_factory=dict)  # open requests
    answered: dict[str, tuple[int, bytes]] = field(default_factory=dict)  # last answers
    action_pubs: dict[str, Callable[[bytes], None]] = field(default_factory=dict)
    member: int = -1  # the run's place in its group (-1: a run alone)

    @property
    def counting(self) -> bool:
        return self.config.explore in ("dis-macb", "cen-macb")

    @property
    def owed_total(self) -> int:
        """Updates the replay ratio asks for so far: one per transition after the warm-up."""
        return max(0, self.ingested - self.config.learning_starts)

    @property
    def done(self) -> bool:
        """Every actor's share of the episodes is in replay and learnt, every weight and
        evaluation point out: the run can complete. (Whether or not an actor's
        "completed" came: a learner resumed after it may never see it.)"""
        return (
            all(self.received.expected(a) >= self.shares[a] for a in self.actors)
            and not any(self.held[a] for a in self.actors)
            and not self.boundaries
            and self.learner.updates >= self.owed_total
            and not self.evaluations.unreported  # every point's row is out (or sent again)
        )


def run_stats(st: LearnerRun, rejects_total: int) -> dict[str, Any]:
    """The run's learner stats: progress, replay ratio and lag, where the time per update
    goes, the bonus queries, the cuts, and the learner's own."""
    updates = st.learner.updates
    owed_total = st.owed_total
    wall = time.perf_counter() - st.t0
    lat = sorted(st.bonus.latencies)
    per_update = 1e3 / updates if updates else 0.0
    phases = {**st.time, "bonus_wait": st.bonus.wait_s}
    spent = {f"ms_per_update_{k}": v * per_update for k, v in phases.items()}
    spent["ms_per_update_other"] = (wall - sum(phases.values())) * per_update
    return {
        "updates": updates,
        "ingested": st.ingested,
        "episodes_ingested": st.episodes,
        "replay_ratio": updates / owed_total if owed_total else 0.0,
        "policy_lag": float(np.mean(st.lags)) if st.lags else 0.0,
        "policy_version": st.version,
        "wall_s": wall,
        "steps_per_sec": st.ingested / wall if wall > 0 else 0.0,
        "updates_per_sec": updates / wall if wall > 0 else 0.0,
        "backlog": owed_total - updates,
        "window_open": st.window_open,
        "bonus_p50_ms": 1e3 * lat[len(lat) // 2] if lat else 0.0,
        "bonus_p99_ms": 1e3 * lat[int(len(lat) * 0.99)] if lat else 0.0,
        "bonus_wait_ms_per_update": spent["ms_per_update_bonus_wait"],
        "bonus_queries": st.bonus.queries,
        "bonus_rows_per_query": st.bonus.rows / max(1, st.bonus.queries),
        "bonus_failures": st.bonus.failures,
        "bonus_mean": float(np.mean(st.bonus_means)) if st.bonus_means else 0.0,
        "rejects_total": rejects_total,
        "contended_updates": st.contended_updates,
        "eval_rows_seen": st.evaluations.reported_rows,
        "cuts": st.cuts,
        "cut_ms_mean": 1e3 * st.cut_s / st.cuts if st.cuts else 0.0,
        "cut_bytes": st.cut_bytes,
        **spent,
        **st.learner.stats(),
    }


def open_error(config: TrainConfig, actors: int) -> str | None:
    """Why the cluster's learner cannot serve this run with this many actors, if so."""
    if config.bonus_at == "collection":
        return (
            "bonus_at collection: the cluster prices bonuses when it samples; run this "
            "config with macb train or as a run group (macb run/reproduce --local)"
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
    pubs: dict[str, Callable[[bytes], None]],
    counter: str | None = None,
    folder: Path | None = None,
    incarnation: str = "",
    member: int = -1,
) -> LearnerRun:
    """A run's state as it starts: an empty replay buffer (no larger than the run),
    the sampler seeded from the run's seed, nothing received, each actor's share of
    the episodes. `pubs` are the run's publishers: weights, eval, ack."""
    return LearnerRun(
        run=run,
        config=config,
        spec=spec,
        learner=learner,
        buffer=ReplayBuffer(
            min(config.buffer_size, config.episodes * config.episode_len),
            spec.joint_obs_dim,
            spec.joint_act_dim,
        ),
        rng=np.random.default_rng(derive_seed(config.seed, "sampler")),
        actors=actors,
        counter=counter,
        bonus=bonus,
        evaluations=evaluations,
        weights_pub=pubs["weights"],
        eval_pub=pubs["eval"],
        ack_pub=pubs["ack"],
        received=ReceiveCursor(actors=actors, partial=False),
        counted=AckTracker(actors),
        held={a: collections.deque() for a in actors},
        minibatches_per_update=minibatches_per_update(config),
        folder=folder,
        shares={
            a: episode_share(config.episodes, len(actors), r) * config.episode_len
            for r, a in enumerate(actors)
        },
        incarnation=incarnation,
        lockstep=config.interleave == "lockstep",
        member=member,
    )
