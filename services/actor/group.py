"""A lockstep run group's actor: its runs' worlds as one VecTask, one act request for all.

World r is run r's. Every step asks the learner for every run's action in one request
on the lead run's keys (run 0), adds each run's own noise and publishes each run's
transition through that run's `Outbox`, so each run is numbered, resent and credited as
a lone run is. The service decides when to step and reports; this holds the worlds.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from services.actor.lockstep import ActExchange
from services.actor.outbox import Outbox
from shared.config import TrainConfig
from shared.envs.tasks import make_task_for
from shared.envs.vectask import vectorize
from shared.net.messages import ActRequest
from shared.net.protocol import Rejoin
from shared.net.wire import encode
from shared.run.rollout import VecCollector, make_vec_collector


@dataclass
class GroupActor:
    """A lockstep group's worlds and, per run, its outbox."""

    actor: str
    runs: list[str]
    cfgs: list[TrainConfig]
    collector: VecCollector
    outboxes: dict[str, Outbox]
    act_pub: Callable[[bytes], None]  # the lead run's act requests
    todo: int  # episodes (every run's)
    episode_len: int
    seq: int = 0  # steps taken (each run's transitions so far)
    done: int = 0
    exchange: ActExchange = field(default_factory=ActExchange)  # answers are (R, joint_act)
    last_stats: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    # restarted: the learner's position of each run, until it has said all of them
    rejoin: Rejoin | None = None

    @classmethod
    def open(
        cls,
        actor: str,
        cfgs: list[TrainConfig],
        outboxes: dict[str, Outbox],
        act_pub: Callable[[bytes], None],
    ) -> GroupActor:
        """Every run of the group has its start (`outboxes` in the group's order)."""
        venv = vectorize([make_task_for(cfg) for cfg in cfgs])
        return cls(
            actor=actor,
            runs=list(outboxes),
            cfgs=cfgs,
            collector=make_vec_collector(cfgs, venv),
            outboxes=outboxes,
            act_pub=act_pub,
            todo=cfgs[0].episodes,
            episode_len=cfgs[0].episode_len,
        )

    @property
    def act_shape(self) -> tuple[int, int]:
        """The shape of the learner's answer (one joint action per run)."""
        return (len(self.runs), len(self.collector.low))

    @property
    def finished(self) -> bool:
        return self.done >= self.todo

    @property
    def settled(self) -> bool:
        """Every run's every batch acknowledged."""
        return all(box.sender.settled for box in self.outboxes.values())

    def resend_due(self, now: float) -> None:
        for box in self.outboxes.values():
            box.resend_due(now)

    def step(self, now: float) -> bool:
        """`ActorRun.lockstep_step` for the group: one step of every run's world per
        answer (True when it was the last), then the next request."""
        act = self.exchange.take(self.seq, now)
        if act is not None:
            tr = self.collector.step(lambda obs: act[:, None])
            for r, run in enumerate(self.runs):
                self.outboxes[run].publish(
                    tr.obs[r : r + 1], tr.act[r : r + 1], tr.rew[r : r + 1],
                    tr.next_obs[r : r + 1], tr.done[r : r + 1], tr.collisions[r : r + 1],
                    -1, now,
                )  # fmt: skip
            self.seq += 1
            if self.seq % self.episode_len == 0:
                self.done += 1
            if self.done >= self.todo:
                return True
        if self.exchange.ask(self.seq, now):
            obs = self.collector.next_obs()
            lead = self.runs[0]
            self.act_pub(encode(ActRequest(lead, actor=self.actor, seq=self.seq, obs=obs)))
        return False

    def rejoin_at(self, positions: dict[str, int]) -> int:
        """The learner and the counter hold `positions` of each run's transitions (the
        least of theirs: `shared.net.protocol.Rejoin`): every world goes on from the least
        (a run ahead by a step gets that step again, which the learner and the counter
        take as a duplicate), with randomness of its own for the rest, as a restarted
        single actor does. Returns that position."""
        position = min(positions.values())
        self.collector = make_vec_collector(self.cfgs, self.collector.venv, steps_done=position)
        for box in self.outboxes.values():
            box.go_on_from(position)
        self.seq, self.done = position, position // self.episode_len
        self.rejoin = None
        self.exchange.forget()
        return position

    def stats(self, run: str, rejects_total: int) -> dict[str, Any]:
        wall = time.perf_counter() - self.t0
        sender = self.outboxes[run].sender
        return {
            "rank": 0,
            "episodes": self.done,
            "published": sender.seq,
            "policy_version": -1,
            "resends": sender.resends,
            "steps_per_sec": self.seq / wall if wall > 0 else 0.0,
            "rejects_total": rejects_total,
            "act_wait_ms": 1e3 * self.exchange.wait_s / self.seq if self.seq else 0.0,
            "group": len(self.runs),
        }
