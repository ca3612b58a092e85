"""Exactly-once delivery of numbered transitions: the rule alone.

Every actor numbers its transitions from 0 and publishes them in batches; the counter
and the learner each keep, per actor, the number of the next transition they expect.
`ReceiveCursor` is that receive rule, `Sender` the actor's side of it (numbering,
the batches not yet acknowledged, when to resend, flow control). They live here, pure
(no bus, no codec), so every service shares one definition and tests can drive every
case in process. When a run is over is the watcher's rule (shared/net/monitor.py).
"""

from __future__ import annotations

import collections
import enum
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any


class Arrival(enum.Enum):
    """A batch [seq, seq + n) from one actor, against the next number expected: what
    its arrival is, and so what a receiver does with it."""

    TAKE = "take"  # starts at the expected number: take it whole
    OVERLAP = "overlap"  # starts below it, ends above: its head was taken before
    DUPLICATE = "duplicate"  # wholly below it: taken before, ignore
    GAP = "gap"  # starts above it: something in between is missing, drop (it is resent)


@dataclass(frozen=True)
class Decision:
    arrival: Arrival
    skip: int = 0  # rows at the head already taken; the rows to keep are [skip:]
    taken: int = 0  # rows taken (0 unless the cursor advanced)

    @property
    def took(self) -> bool:
        return self.taken > 0


def decide(expected: int, seq: int, n: int) -> Decision:
    """The rule itself, for one batch against the next expected number."""
    if seq + n <= expected:
        return Decision(Arrival.DUPLICATE, skip=n)
    if seq > expected:
        return Decision(Arrival.GAP)
    if seq == expected:
        return Decision(Arrival.TAKE, skip=0, taken=n)
    return Decision(Arrival.OVERLAP, skip=expected - seq, taken=seq + n - expected)


class ReceiveCursor:
    """The next expected transition number per actor, advanced by `take`.

    `partial=False` (the learner: a batch is one whole episode, its replay and episode
    boundaries count episodes) refuses an overlapping batch instead of taking its tail:
    it is reported as OVERLAP with nothing taken, and the sender resends from the ack.
    `actors` restricts the cursor to known actors (`take` of another raises KeyError);
    without it any actor starts at 0.
    """

    def __init__(
        self,
        expected: Mapping[str, int] | None = None,
        actors: Iterable[str] | None = None,
        partial: bool = True,
    ) -> None:
        self.partial = partial
        self.fixed = actors is not None
        self._next: dict[str, int] = dict.fromkeys(actors, 0) if actors is not None else {}
        for actor, seq in (expected or {}).items():
            if self.fixed and actor not in self._next:
                raise KeyError(f"unknown actor: {actor}")
            self._next[actor] = int(seq)
        self.duplicate_rows = 0
        self.gaps = 0

    def knows(self, actor: str) -> bool:
        return not self.fixed or actor in self._next

    def expected(self, actor: str) -> int:
        if not self.knows(actor):
            raise KeyError(f"unknown actor: {actor}")
        return self._next.get(actor, 0)

    def peek(self, actor: str, seq: int, n: int) -> Decision:
        """What `take` would decide, without advancing."""
        d = decide(self.expected(actor), seq, n)
        if d.arrival is Arrival.OVERLAP and not self.partial:
            return Decision(Arrival.OVERLAP, skip=d.skip)
        return d

    def take(self, actor: str, seq: int, n: int) -> Decision:
        """Decide on batch [seq, seq + n) of `actor`; advance past what is taken."""
        d = self.peek(actor, seq, n)
        if d.took:
            self._next[actor] = seq + n
        if d.took or d.arrival is Arrival.DUPLICATE:
            self.duplicate_rows += d.skip
        else:
            self.gaps += 1  # a gap, or an overlap refused whole: the sender resends
        return d

    def positions(self) -> dict[str, int]:
        """Actor -> next expected number: what an ack carries and a snapshot stores."""
        return dict(self._next)

    def copy(self) -> ReceiveCursor:
        """A staging copy: decide a burst on it, commit it once the burst is durable."""
        other = ReceiveCursor(partial=self.partial)
        other.fixed, other._next = self.fixed, dict(self._next)
        other.duplicate_rows, other.gaps = self.duplicate_rows, self.gaps
        return other


class AckTracker:
    """How far each service has acknowledged each actor: acks only move forward.

    The learner uses one for the counter's acks (a batch joins replay once counted);
    `Sender` one per receiver of its batches.
    """

    def __init__(self, actors: Iterable[str] = ()) -> None:
        self._acked: dict[str, int] = dict.fromkeys(actors, 0)

    def ack(self, actor: str, seq: Any) -> bool:
        """Record an ack; True when it moved forward. Non-int or unknown acks are ignored."""
        if not isinstance(seq, int) or isinstance(seq, bool) or actor not in self._acked:
            return False
        if seq > self._acked[actor]:
            self._acked[actor] = seq
            return True
        return False

    def covers(self, actor: str, seq: int, n: int) -> bool:
        """Batch [seq, seq + n) is acknowledged whole."""
        return seq + n <= self._acked.get(actor, 0)

    def __getitem__(self, actor: str) -> int:
        return self._acked[actor]


def episode_share(episodes: int, actors: int, rank: int) -> int:
    """Episodes actor `rank` runs: the run's total split as evenly as possible."""
    return episodes // actors + (1 if rank < episodes % actors else 0)


@dataclass
class Sender:
    """One actor's sending side: numbering, the unacknowledged batches, resends, credit.

    `confirm` are the services that must acknowledge a batch before it is forgotten
    (the learner, and the counter when the run counts). `credit_from` grants a window:
    a batch may go out only while it ends within that service's ack plus its window.
    `bounded` services may fall at most `max_unconfirmed` batches behind (the counter
    has no window of its own; while it is down the actor stops after that many).
    A batch is resent after `resend_after_s` without any ack moving forward.
    """

    confirm: Sequence[str]
    credit_from: str
    bounded: Sequence[str] = ()
    max_unconfirmed: int = 8
    resend_after_s: float = 1.0
    seq: int = 0  # number of the next transition
    window: int = 0  # the latest credit granted, in transitions
    resends: int = 0
    last_progress: float = 0.0
    unacked: collections.deque[tuple[int, int, bytes]] = field(default_factory=collections.deque)
    acked: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for svc in (*self.confirm, self.credit_from, *self.bounded):
            self.acked.setdefault(svc, 0)

    def can_send(self, n: int) -> bool:
        """A batch of n rows may go out now (credit left, no bounded service too far behind)."""
        if self.seq + n > self.acked[self.credit_from] + self.window:
            return False
        return all((self.seq - self.acked[s]) // n < self.max_unconfirmed for s in self.bounded)

    def send(self, n: int, payload: bytes, now: float) -> int:
        """Number a batch of n rows (its payload already carries `seq`); keep it until acked."""
        if not self.unacked:
            self.last_progress = now  # the resend clock starts with the first batch in flight
        seq = self.seq
        self.unacked.append((seq, n, payload))
        self.seq += n
        return seq

    def on_ack(self, service: str, seq: Any, now: float, window: int | None = None) -> None:
        """An ack from `service` for this actor: record it, take its window, forget batches."""
        if service not in self.acked or not isinstance(seq, int) or isinstance(seq, bool):
            return
        if seq > self.acked[service]:
            self.last_progress = now
        self.acked[service] = max(self.acked[service], seq)
        if window is not None and service == self.credit_from:
            self.window = int(window)
        fully = min(self.acked[s] for s in self.confirm) if self.confirm else self.seq
        while self.unacked and self.unacked[0][0] + self.unacked[0][1] <= fully:
            self.unacked.popleft()

    def due(self, now: float) -> list[bytes]:
        """Payloads to resend now: all unacknowledged ones once no ack moved for a while."""
        if not self.unacked or now - self.last_progress <= self.resend_after_s:
            return []
        self.last_progress = now
        self.resends += len(self.unacked)
        return [payload for _, _, payload in self.unacked]

    @property
    def settled(self) -> bool:
        """Every batch sent has been acknowledged by every service that must confirm it."""
        return not self.unacked


@dataclass
class Rejoin:
    """Where a restarted actor goes on with each of its runs: the least of what the
    learner and (for a counting run) the counter acknowledge of it. Both matter: after
    two faults at once one of them may lack a batch the dead actor had in flight, and
    only a batch sent again (collected anew from there) fills it; the other drops it as
    a duplicate. The counter's ack may not come (it is down, or it does not know the
    run's actors and has counted nothing of it), so it is waited for at most
    `counter_wait_s`, then the learner's position is taken."""

    learner: str
    counter: str | None  # None: the run counts nothing
    since: float
    counter_wait_s: float = 3.0
    learner_at: dict[str, int] = field(default_factory=dict)  # run -> position
    counter_at: dict[str, int] = field(default_factory=dict)

    def ack(self, run: str, service: str, position: Any) -> None:
        if not isinstance(position, int) or isinstance(position, bool) or position < 0:
            return
        if service == self.learner:
            self.learner_at[run] = position
        elif service == self.counter:
            self.counter_at[run] = position

    def positions(self, runs: list[str], now: float) -> dict[str, int] | None:
        """Each run's position once known (None: keep waiting)."""
        if any(run not in self.learner_at for run in runs):
            return None
        waited = now - self.since >= self.counter_wait_s
        if self.counter and not waited and any(run not in self.counter_at for run in runs):
            return None
        return {
            run: min(self.learner_at[run], self.counter_at.get(run, self.learner_at[run]))
            for run in runs
        }


# ----------------------------------------------------------------------- run status
RUN_STATES = ("running", "finishing", "completed", "stopped", "failed")
