"""What an actor holds for the runs it serves, and how it steps them: a run alone is a
group of one, so a lone run and a lockstep group's R runs are served by the same code.

World r is run r's. A run alone steps its own world through its `Collector` (rank
`rank` of its actors, seeded as `macb train` seeds it); a group (`grouped`: the
assignment names its runs) steps its runs' worlds as one VecTask through a
`VecCollector`. Either is read here as (R, ...) steps. Async (a run alone): whole
episodes with the newest weights loaded (`run_episode`). Lockstep: one step of every
world per answer of the learner (`lockstep_step`), asked in one request on the lead
run's keys (run 0). Each run's transitions go out numbered through its own `Outbox`;
the service decides when (credit, rejoining, weights) and reports.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.actor.lockstep import ActExchange
from services.actor.outbox import Outbox
from shared.config import TrainConfig
from shared.core.networks import JointPolicy
from shared.envs.tasks import TaskEnv, make_task_for
from shared.envs.vectask import ListTask, VecTask, vectorize
from shared.net.messages import ActRequest, Weights
from shared.net.protocol import Rejoin, episode_share
from shared.net.stats import ActorStats
from shared.net.wire import encode
from shared.run.rollout import (
    Collector,
    Transition,
    VecCollector,
    VecTransitions,
    make_collector,
    make_vec_collector,
)

ActFor = Callable[[np.ndarray], np.ndarray]  # every run's joint obs (R, O) -> actions (R, A)


def one_of(t: Transition) -> VecTransitions:
    """A lone run's step as a group of one's: (1, ...) arrays."""
    return VecTransitions(
        t.obs[None], t.act[None], np.array([t.rew]), t.next_obs[None], np.array([t.done]),
        np.array([t.success]), np.array([t.collisions]), np.array([t.episode_end]),
    )  # fmt: skip


@dataclass
class ActorRuns:
    """The runs served (`outboxes`, in the group's order; one for a run alone), their
    worlds, and where the actor is in them."""

    actor: str
    cfgs: list[TrainConfig]
    outboxes: dict[str, Outbox]  # numbering, unacknowledged batches, resends, credit
    world: Any  # a run alone's TaskEnv, or a group's VecTask (world r is run r's)
    collector: Collector | VecCollector
    todo: int  # episodes this actor runs (of each run)
    rank: int = 0  # its place among the run's actors (a group has one actor)
    actors: int = 1
    grouped: bool = False  # a group's runs (its act requests carry every run's obs)
    policy: JointPolicy | None = None  # async: the actors acting, as the learner sent them
    act_pub: Callable[[bytes], None] | None = None  # lockstep: the lead run's act requests
    version: int = -1  # weights version acting now; -1 until the learner's first weights
    incarnation: Any = None  # the learner process whose weights those are
    looked_at: object = None  # the newest weights message last looked at (decoded once)
    rejoin: Rejoin | None = None  # restarted: waiting to hear where each run goes on
    done: int = 0
    steps: int = 0  # steps taken by this process (each run's)
    last_stats: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    exchange: ActExchange = field(default_factory=ActExchange)  # lockstep
    # A group's runs their `early_stop` rule ended while the others go on: their worlds
    # still step (every world steps as one), their transitions are not published.
    stopped: set[str] = field(default_factory=set)

    @classmethod
    def open(
        cls,
        actor: str,
        cfgs: list[TrainConfig],
        outboxes: dict[str, Outbox],
        act_pub: Callable[[bytes], None] | None = None,
        rank: int = 0,
        actors: int = 1,
        grouped: bool = False,
    ) -> ActorRuns:
        """Every run's start has come (`outboxes` in the group's order): the worlds
        seeded for `rank`, untrained actors when async."""
        cfg = cfgs[0]
        world: VecTask | ListTask | TaskEnv
        collector: Collector | VecCollector
        if grouped:
            world = vec = vectorize([make_task_for(c) for c in cfgs])
            collector = make_vec_collector(cfgs, vec)
        else:
            world = one = make_task_for(cfg)
            collector = make_collector(cfg, one, rank, actors)
        return cls(
            actor=actor,
            cfgs=cfgs,
            outboxes=outboxes,
            world=world,
            collector=collector,
            todo=episode_share(cfg.episodes, actors, rank),
            rank=rank,
            actors=actors,
            grouped=grouped,
            policy=None if act_pub else JointPolicy.for_task(world.spec, cfg.hidden),
            act_pub=act_pub,
        )

    @property
    def runs(self) -> list[str]:
        return list(self.outboxes)

    @property
    def going(self) -> list[str]:
        """The runs still served: all of them but those their rule ended."""
        return [r for r in self.outboxes if r not in self.stopped]

    @property
    def lead(self) -> Outbox:
        """The first run still going: its numbering paces the steps (every run's is
        the same in lockstep)."""
        return self.outboxes[self.going[0]]

    @property
    def lockstep(self) -> bool:
        return self.act_pub is not None

    @property
    def episode_len(self) -> int:
        return self.cfgs[0].episode_len

    @property
    def act_shape(self) -> tuple[int, ...]:
        """The shape of the learner's answer: a joint action, one per run for a group."""
        n = len(self.collector.low)
        return (len(self.cfgs), n) if self.grouped else (n,)

    @property
    def finished(self) -> bool:
        return self.done >= self.todo

    @property
    def settled(self) -> bool:
        """Every run's every batch acknowledged."""
        return all(self.outboxes[r].sender.settled for r in self.going)

    def resend_due(self, now: float) -> None:
        for r in self.going:
            self.outboxes[r].resend_due(now)

    def newer(self, msg: Weights) -> bool:
        """`msg`'s actors are newer than those acting: a higher version, or any version
        of another learner process (a restarted learner numbers on from its last cut, so
        its weights are newer than any of the process before, whatever their number)."""
        return msg.version > self.version or msg.incarnation != self.incarnation

    def load_weights(self, msg: Weights) -> bool:
        """Act with `msg`'s actors if they are `newer` (checked against the policy's
        layout before: `shared.core.networks.weights_error`)."""
        if not self.newer(msg):
            return False
        assert self.policy is not None
        self.policy.load(msg.actors)
        self.version = msg.version
        self.incarnation = msg.incarnation
        return True

    def step(self, act_for: ActFor) -> VecTransitions:
        """One step of every world."""
        c = self.collector
        if isinstance(c, VecCollector):
            return c.step(lambda obs: act_for(obs[:, 0])[:, None])
        return one_of(c.step(act_for))

    def publish(self, steps: list[VecTransitions], now: float) -> None:
        """Each run's rows of `steps` as one numbered batch on its keys."""
        for r, (run, box) in enumerate(self.outboxes.items()):
            if run in self.stopped:
                continue  # (its world stepped, unread: as in the one-process group)
            obs, act, rew, next_obs, done, collisions = (
                np.concatenate([getattr(t, k)[r : r + 1] for t in steps])
                for k in ("obs", "act", "rew", "next_obs", "done", "collisions")
            )
            box.publish(obs, act, rew, next_obs, done, collisions, self.version, now)
        self.steps += len(steps)

    def run_episode(self) -> None:
        """Async: one episode with the weights loaded, published as one batch."""
        assert self.policy is not None
        steps = [self.step(self.policy) for _ in range(self.episode_len)]
        self.publish(steps, time.monotonic())
        self.done += 1

    def lockstep_step(self, now: float) -> bool:
        """The answered step of every world, if its action has come (True when it was
        the share's last), then the request for the next one at once (the learner
        answers it after learning this one), or again if unanswered too long."""
        assert self.act_pub is not None
        seq = self.lead.sender.seq
        act = self.exchange.take(seq, now)
        if act is not None:
            answer = act if self.grouped else act[None]
            self.publish([self.step(lambda obs: answer)], time.monotonic())
            seq = self.lead.sender.seq
            if seq % self.episode_len == 0:
                self.done += 1
            if self.finished:
                return True
        if self.exchange.ask(seq, now):
            obs = self.collector.next_obs()
            run, actor = self.runs[0], self.actor  # (on the lead run's keys, as it began)
            self.act_pub(encode(ActRequest(run, actor=actor, seq=seq, obs=obs)))
        return False

    def rejoin_at(self, positions: dict[str, int]) -> int:
        """The learner and the counter hold `positions` of each run's transitions (the
        least of theirs: `shared.net.protocol.Rejoin`): every world goes on from the
        least (async: whole episodes only, as they are; a group's run ahead by a step
        gets that step again, which the learner and the counter take as a duplicate),
        with randomness of that position. Returns where it goes on."""
        position = min(positions.values())
        if not self.lockstep:
            position -= position % self.episode_len
        if isinstance(self.collector, VecCollector):
            self.collector = make_vec_collector(self.cfgs, self.world, steps_done=position)
        else:
            self.collector = make_collector(
                self.cfgs[0], self.world, self.rank, self.actors, steps_done=position
            )
        for box in self.outboxes.values():
            box.go_on_from(position)
        self.done = position // self.episode_len
        self.rejoin = None
        self.exchange.forget()
        return position

    def stats(self, run: str, rejects_total: int) -> ActorStats:
        wall = time.perf_counter() - self.t0
        sender = self.outboxes[run].sender
        return ActorStats(
            rank=self.rank,
            episodes=self.done,
            published=sender.seq,
            policy_version=self.version,
            resends=sender.resends,
            steps_per_sec=self.steps / wall if wall > 0 else 0.0,
            rejects_total=rejects_total,
            # lockstep: mean time from an act request to its action (the learner's
            # update, the count before it and the bus's round trips)
            act_wait_ms=(
                1e3 * self.exchange.wait_s / self.steps if self.lockstep and self.steps else 0.0
            ),
            group=len(self.cfgs) if self.grouped else None,
        )
