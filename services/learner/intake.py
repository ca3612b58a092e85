"""Exactly-once intake: a batch taken from an actor is logged, held until the counter
has counted it, then added to replay once; replayed from the log after a restart.

`Intake` is the run's intake state (the replay buffer, what was taken from each actor,
what the counter counted, the episode boundaries ingested, the log) and this module its
one writer; the others read it or call its methods (the boundaries due, a cut's counters
in and out, the log opened and closed). Pure (no bus): the service decodes, calls
`take`, and acknowledges what the cursor says. Every sampled transition has been
counted (n >= 1), and the boundaries of the episodes ingested say when weights go out.
"""

from __future__ import annotations

import collections
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from shared.core.replay import ReplayBuffer
from shared.net.messages import Transitions
from shared.net.protocol import AckTracker, ReceiveCursor
from shared.net.wire import check_batch_rows, check_dims
from shared.persist.wal import WriteAheadLog

if TYPE_CHECKING:
    from services.learner.state import LearnerRun

# A logged batch's columns, as the write-ahead log stores them.
LOG_COLUMNS = (
    ("obs", np.float32),
    ("act", np.float32),
    ("rew", np.float32),
    ("next_obs", np.float32),
    ("done", np.float32),
    ("collisions", np.int32),
    ("policy_version", np.int32),
)


class Boundary(NamedTuple):
    """An ingested episode's end: weights go out once `updates` updates are done."""

    episode: int
    updates: int
    env_steps: int
    collisions_cum: int


@dataclass
class Intake:
    """A run's transitions from its actors to its replay buffer."""

    buffer: ReplayBuffer
    received: ReceiveCursor  # what has been taken from each actor (whole episodes only)
    counted: AckTracker  # how far the counter has acknowledged each actor
    held: dict[str, collections.deque[Transitions]]  # received, not yet counted
    shares: dict[str, int]  # transitions each actor owes
    ingested: int = 0
    episodes: int = 0
    collisions_cum: int = 0
    boundaries: collections.deque[Boundary] = field(default_factory=collections.deque)
    ingested_pos: dict[str, int] = field(default_factory=dict)  # per actor, in replay
    lags: collections.deque[int] = field(default_factory=lambda: collections.deque(maxlen=200))
    log: WriteAheadLog | None = None  # every batch taken, before it is acknowledged

    @classmethod
    def open(cls, capacity: int, obs_dim: int, act_dim: int, shares: dict[str, int]) -> Intake:
        """Nothing taken yet: an empty buffer, each actor's share of the transitions."""
        actors = list(shares)
        return cls(
            buffer=ReplayBuffer(capacity, obs_dim, act_dim),
            received=ReceiveCursor(actors=actors, partial=False),
            counted=AckTracker(actors),
            held={a: collections.deque() for a in actors},
            shares=shares,
        )

    def all_in(self) -> bool:
        """Every actor's share is taken and counted into replay."""
        return all(self.received.expected(a) >= n for a, n in self.shares.items()) and not any(
            self.held.values()
        )

    def in_replay(self, actor: str, seq: int) -> bool:
        """Every step of `actor` before `seq` is counted and in replay, and no later one."""
        return self.ingested_pos.get(actor, 0) == seq and not self.held[actor]

    def boundary_done(self, updates: int) -> Boundary | None:
        """The next episode boundary, taken, once its `updates` are done."""
        if self.boundaries and updates >= self.boundaries[0].updates:
            return self.boundaries.popleft()
        return None

    def restore(
        self, counters: dict[str, Any], ingested_pos: dict, boundaries: Iterable[Iterable]
    ) -> None:
        """A cut's counters, before its log is replayed."""
        self.ingested = int(counters["ingested"])
        self.episodes = int(counters["episodes"])
        self.collisions_cum = int(counters["collisions_cum"])
        self.ingested_pos = {str(a): int(p) for a, p in ingested_pos.items()}
        self.boundaries = collections.deque(Boundary(*map(int, b)) for b in boundaries)

    def open_log(self, path: Path) -> list:
        """The log opened for appending, and what an earlier process of this learner took
        (a torn last record is cut off: it was never acked)."""
        self.log, records = WriteAheadLog.open(path)
        return records

    def close_log(self) -> None:
        if self.log is not None:
            self.log.close()
            self.log = None


def take(st: LearnerRun, msg: Transitions) -> bool:
    """Take a batch if it is the next one of its actor (a duplicate or a gap is not
    taken: the ack tells the actor where we are); True if taken. Refuses a batch of
    another layout or length with WireError."""
    check_dims(msg, st.spec.joint_obs_dim, st.spec.joint_act_dim)
    check_batch_rows(msg, st.config.episode_len, st.lockstep)  # (the counter's rule too)
    n, it = len(msg), st.intake
    if not it.received.peek(msg.actor, msg.seq, n).took:
        it.received.take(msg.actor, msg.seq, n)  # (counts the duplicate or the gap)
        return False
    # Logged before the cursor moves (and before the ack says we have it): a batch
    # that cannot be logged raises with nothing taken, and its resend is taken (taken
    # first, the resend was a duplicate, in neither the log nor replay).
    if it.log is not None:
        it.log.append(msg.actor, msg.seq, n, log_columns(msg))
    it.received.take(msg.actor, msg.seq, n)
    it.held[msg.actor].append(msg)
    release_counted(st)
    return True


def counter_acked(st: LearnerRun, acked: dict[str, Any]) -> None:
    """The counter's ack: how far it has counted each actor's transitions."""
    for actor, seq in acked.items():
        st.intake.counted.ack(actor, seq)
    release_counted(st)


def release_counted(st: LearnerRun) -> None:
    """Move batches the counter has counted (or all, with no counting) into replay."""
    it = st.intake
    for actor, held in it.held.items():
        while held and (not st.counting or it.counted.covers(actor, held[0].seq, len(held[0]))):
            ingest(st, held.popleft())


def ingest(st: LearnerRun, msg: Transitions) -> None:
    """Into replay: its rows, its episode's end as a boundary, the counters."""
    n, seq, length, it = len(msg), msg.seq, st.config.episode_len, st.intake
    it.buffer.add(msg.obs, msg.act, msg.rew, msg.next_obs, msg.done)
    it.ingested += n
    it.ingested_pos[msg.actor] = seq + n
    it.collisions_cum += int(msg.collisions.sum())
    # Lockstep: every action came from the weights of that moment (no lag).
    it.lags.append(0 if st.lockstep else st.outgoing.version - msg.policy_version)
    if (seq + n) // length > seq // length:  # the batch ends one of the actor's episodes
        it.episodes += 1
        it.boundaries.append(Boundary(it.episodes, st.owed_total, it.ingested, it.collisions_cum))


def replay(st: LearnerRun, records: list) -> tuple[list[str], int]:
    """The log beyond the cut: batches in replay at the cut refill the buffer; those
    taken but not yet counted wait for the counter's ack again. Returns the batches
    skipped as out of order, as 'actor@seq', and the newest weights version an actor
    acted with (the weights sent from now on are newer: the lags stay >= 0)."""
    skipped, newest, it = [], -1, st.intake
    for rec in records:
        rows = columns(rec.keys, rec.n)
        if not it.received.take(rec.actor, rec.seq, rec.n).took:
            skipped.append(f"{rec.actor}@{rec.seq}")
            continue
        newest = max(newest, int(rows["policy_version"]))
        if rec.seq < it.ingested_pos.get(rec.actor, 0):  # in replay at the cut
            it.buffer.add(rows["obs"], rows["act"], rows["rew"], rows["next_obs"], rows["done"])
        else:  # taken, not yet counted at the cut: waits for the counter's ack again
            it.held[rec.actor].append(Transitions(st.run, rec.actor, rec.seq, **rows))
    return skipped, newest


def log_columns(msg: Transitions) -> list[np.ndarray]:
    """A transitions batch as the log's byte columns (LOG_COLUMNS)."""
    n = len(msg)
    out = []
    for name, dtype in LOG_COLUMNS:
        if name == "policy_version":
            col = np.full(n, msg.policy_version, dtype)
        else:
            col = np.ascontiguousarray(getattr(msg, name), dtype=dtype)
        out.append(col.reshape(n, -1).view(np.uint8))
    return out


def columns(cols: list[np.ndarray], n: int) -> dict[str, Any]:
    """The log's byte columns back as a batch (the inverse of log_columns)."""
    if len(cols) != len(LOG_COLUMNS):
        raise ValueError(f"a logged batch has {len(cols)} columns, expected {len(LOG_COLUMNS)}")
    out: dict[str, Any] = {}
    for (name, dtype), col in zip(LOG_COLUMNS, cols):
        values = np.ascontiguousarray(col).view(dtype).reshape(n, -1)
        if name in ("rew", "done", "collisions"):
            values = values[:, 0]
        out[name] = int(values[0, 0]) if name == "policy_version" else values
    return out
