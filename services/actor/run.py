"""What an actor holds for the one run it serves, and how it steps it.

Async: whole episodes with the newest weights it has loaded (`run_episode`). Lockstep:
one step per action the learner answers (`lockstep_step`). Both publish through the
run's `Outbox`; the service decides when (credit, rejoining, weights) and reports.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from services.actor.lockstep import ActExchange
from services.actor.outbox import Outbox
from shared.config import TrainConfig
from shared.core.networks import JointPolicy
from shared.envs.tasks import TaskEnv, make_task_for
from shared.net.messages import ActRequest, Weights
from shared.net.protocol import Rejoin, episode_share
from shared.net.wire import encode
from shared.run.rollout import Collector, make_collector


@dataclass
class ActorRun:
    """Rank `rank` of `actors` on a run: its world, its copy of the actors, its share."""

    config: TrainConfig
    rank: int
    actors: int
    env: TaskEnv
    collector: Collector
    policy: JointPolicy
    todo: int  # episodes this actor runs
    outbox: Outbox  # numbering, unacknowledged batches, resends, credit
    version: int = -1  # weights version acting now; -1 until the learner's first weights
    incarnation: Any = None  # the learner process whose weights those are
    rejoin: Rejoin | None = None  # restarted: waiting to hear where to go on
    done: int = 0
    steps: int = 0
    last_stats: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    act_pub: Callable[[bytes], None] | None = None  # lockstep: where act requests go
    exchange: ActExchange = field(default_factory=ActExchange)  # lockstep

    @classmethod
    def open(
        cls,
        config: TrainConfig,
        rank: int,
        actors: int,
        outbox: Outbox,
        act_pub: Callable[[bytes], None] | None = None,
    ) -> ActorRun:
        """A run's start: its world and collector seeded for `rank`, untrained actors."""
        env = make_task_for(config)
        return cls(
            config=config,
            rank=rank,
            actors=actors,
            env=env,
            collector=make_collector(config, env, rank, actors),
            policy=JointPolicy.for_task(env.spec, config.hidden),
            todo=episode_share(config.episodes, actors, rank),
            outbox=outbox,
            act_pub=act_pub,
        )

    @property
    def lockstep(self) -> bool:
        return self.act_pub is not None

    @property
    def act_shape(self) -> tuple[int, ...]:
        """The shape of the learner's answer (one joint action)."""
        return self.collector.low.shape

    def load_weights(self, msg: Weights) -> bool:
        """Act with `msg`'s actors if they are newer: a higher version, or any version of
        another learner process (a restarted learner numbers on from its last cut, so its
        weights are newer than any of the process before, whatever their number)."""
        if msg.version <= self.version and msg.incarnation == self.incarnation:
            return False
        self.policy.load(msg.actors)
        self.version = msg.version
        self.incarnation = msg.incarnation
        return True

    def run_episode(self) -> None:
        """One episode with the weights loaded, published as one batch."""
        collector, policy = self.collector, self.policy
        rows = [collector.step(policy) for _ in range(self.config.episode_len)]
        self.outbox.publish_rows(rows, self.version, time.monotonic())
        self.done += 1
        self.steps += len(rows)

    def lockstep_step(self, now: float) -> bool:
        """The answered step, if its action has come (True when it was the share's last),
        then the request for the next one at once (the learner answers it after learning
        this one), or again if unanswered too long."""
        assert self.act_pub is not None
        seq = self.outbox.sender.seq
        act = self.exchange.take(seq, now)
        if act is not None:
            self.outbox.publish_rows(
                [self.collector.step(lambda obs: act[None])], self.version, time.monotonic()
            )
            self.steps += 1
            if self.outbox.sender.seq % self.config.episode_len == 0:
                self.done += 1
            if self.done >= self.todo:
                return True
            seq = self.outbox.sender.seq
        if self.exchange.ask(seq, now):
            obs = self.collector.next_obs()
            run, actor = self.outbox.run, self.outbox.actor
            self.act_pub(encode(ActRequest(run, actor=actor, seq=seq, obs=obs)))
        return False

    def rejoin_at(self, position: int) -> int:
        """The learner and the counter hold `position` of our transitions (the least of
        theirs: `shared.net.protocol.Rejoin`): go on from there, with randomness of that
        position. Returns where it goes on (async: whole episodes only, as they are)."""
        if not self.lockstep:
            position -= position % self.config.episode_len
        self.outbox.go_on_from(position)
        self.done = position // self.config.episode_len
        self.collector = make_collector(
            self.config, self.env, self.rank, self.actors, steps_done=position
        )
        self.rejoin = None
        return position

    def stats(self, rejects_total: int) -> dict[str, Any]:
        wall = time.perf_counter() - self.t0
        sender = self.outbox.sender
        return {
            "rank": self.rank,
            "episodes": self.done,
            "published": sender.seq,
            "policy_version": self.version,
            "resends": sender.resends,
            "steps_per_sec": self.steps / wall if wall > 0 else 0.0,
            "rejects_total": rejects_total,
            # lockstep: mean time from an act request to its action (the learner's
            # update, the count before it and the bus's round trips)
            "act_wait_ms": (
                1e3 * self.exchange.wait_s / self.steps if self.lockstep and self.steps else 0.0
            ),
        }
