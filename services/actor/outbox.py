"""An actor's transitions on their way to a run's learner and counter.

Each batch is numbered, published, and kept until every service that must confirm it
has; it goes out again after a while without progress (`shared.net.protocol.Sender`
holds that rule). The outbox only publishes through the callable it is given, so the
numbering, the resends and the rejoin position are tested without a bus.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from shared.config import TrainConfig
from shared.net.messages import Assignment, Transitions
from shared.net.protocol import Rejoin, Sender
from shared.net.wire import encode, transitions_error
from shared.run.rollout import Transition

MAX_UNCOUNTED_BATCHES = 8  # episodes in flight that the counter has not acknowledged
RESEND_AFTER_S = 1.0


def run_sender(config: TrainConfig, assign: Assignment) -> Sender:
    """A run's numbering, resends and credit: confirmed by its learner and, when it
    counts, its counter (which also bounds what may be in flight uncounted)."""
    learner = assign.learner
    counter = assign.counter if config.counts else None  # its counter confirms them too
    return Sender(
        confirm=(learner,) if counter is None else (learner, counter),
        credit_from=learner,
        bounded=() if counter is None else (counter,),
        max_unconfirmed=MAX_UNCOUNTED_BATCHES,
        resend_after_s=RESEND_AFTER_S,
        last_progress=time.monotonic(),
    )


def rejoin_from(assign: Assignment, cfgs: Sequence[TrainConfig], now: float) -> Rejoin:
    """A restarted actor's wait for where to go on: the learner's ack and, when any of
    its runs counts, the counter's (`shared.net.protocol.Rejoin`)."""
    counter = assign.counter if any(c.counts for c in cfgs) else None
    return Rejoin(assign.learner, counter, since=now)


class BadWorld(Exception):
    """A run's steps gave rows that no learner or counter takes (a NaN or an infinite
    observation or reward from a custom task, an action from a learner gone to NaN):
    the run fails saying so, instead of the batch being resent and refused forever."""


def transitions_payload(
    run: str, actor: str, seq: int, obs, act, rew, next_obs, done, collisions, version: int
) -> bytes:
    """One numbered `transitions` batch (rows seq, seq+1, ...) as the wire carries it;
    `BadWorld` for one the receivers would refuse."""
    msg = Transitions(
        run,
        actor=actor,
        seq=seq,
        obs=np.asarray(obs, np.float32),
        act=np.asarray(act, np.float32),
        rew=np.asarray(rew, np.float32),
        next_obs=np.asarray(next_obs, np.float32),
        done=np.asarray(done, np.float32),
        collisions=np.asarray(collisions, np.int32),
        policy_version=version,
    )
    if why := transitions_error(msg):
        raise BadWorld(f"run {run}: its steps gave rows no learner takes, from row {seq} ({why})")
    return encode(msg)


@dataclass
class Outbox:
    """One run's transitions from this actor: numbered from `sender.seq`, published on
    `pub`, kept by `sender` until confirmed."""

    run: str
    actor: str
    sender: Sender
    pub: Callable[[bytes], None]

    def publish(self, obs, act, rew, next_obs, done, collisions, version: int, now: float) -> None:
        """Publish rows as one numbered batch (resent until acknowledged)."""
        payload = transitions_payload(
            self.run, self.actor, self.sender.seq, obs, act, rew, next_obs, done, collisions,
            version,
        )  # fmt: skip
        self.sender.send(len(obs), payload, now)
        self.pub(payload)

    def publish_rows(self, rows: list[Transition], version: int, now: float) -> None:
        """`publish` for a collector's transitions, stacked into one batch."""
        self.publish(
            np.stack([t.obs for t in rows]), np.stack([t.act for t in rows]),
            np.array([t.rew for t in rows]), np.stack([t.next_obs for t in rows]),
            np.array([t.done for t in rows]), np.array([t.collisions for t in rows]),
            version, now,
        )  # fmt: skip

    def resend_due(self, now: float) -> None:
        """Batches due for a resend go out again."""
        for payload in self.sender.due(now):
            self.pub(payload)

    def go_on_from(self, position: int) -> None:
        """Rejoined: the learner and the counter hold `position` transitions; number on
        from there as if each had acknowledged exactly that."""
        self.sender.seq = position
        for svc in self.sender.acked:
            self.sender.acked[svc] = position
