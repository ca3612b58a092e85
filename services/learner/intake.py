"""Exactly-once intake: a batch taken from an actor is logged, held until the counter
has counted it, then added to replay once; replayed from the log after a restart.

Pure over a `LearnerRun` (no bus): the service decodes, calls `take`, and acknowledges
what the cursor says. Every sampled transition has been counted (n >= 1), and the
boundaries of the episodes ingested say when weights go out.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from services.learner.state import Boundary, LearnerRun
from shared.net.messages import Transitions
from shared.net.wire import WireError, check_dims

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


def take(st: LearnerRun, msg: Transitions) -> bool:
    """Take a batch if it is the next one of its actor (a duplicate or a gap is not
    taken: the ack tells the actor where we are); True if taken. Refuses a batch of
    another layout or length with WireError."""
    check_dims(msg, st.spec.joint_obs_dim, st.spec.joint_act_dim)
    n = len(msg)
    if n != (1 if st.lockstep else st.config.episode_len):
        length = st.config.episode_len
        what = "one step (lockstep)" if st.lockstep else f"one episode ({length})"
        raise WireError(f"transitions: a batch is {what}, got {n}")
    if not st.received.take(msg.actor, msg.seq, n).took:
        return False
    if st.log is not None:  # logged before the ack says we have it
        st.log.append(msg.actor, msg.seq, n, log_columns(msg))
    st.held[msg.actor].append(msg)
    release_counted(st)
    return True


def release_counted(st: LearnerRun) -> None:
    """Move batches the counter has counted (or all, with no counting) into replay."""
    for actor, held in st.held.items():
        while held and (not st.counting or st.counted.covers(actor, held[0].seq, len(held[0]))):
            ingest(st, held.popleft())


def ingest(st: LearnerRun, msg: Transitions) -> None:
    """Into replay: its rows, its episode's end as a boundary, the counters."""
    n, seq, length = len(msg), msg.seq, st.config.episode_len
    st.buffer.add(msg.obs, msg.act, msg.rew, msg.next_obs, msg.done)
    st.ingested += n
    st.ingested_pos[msg.actor] = seq + n
    st.collisions_cum += int(msg.collisions.sum())
    # Lockstep: every action came from the weights of that moment (no lag).
    st.lags.append(0 if st.lockstep else st.version - msg.policy_version)
    if (seq + n) // length > seq // length:  # the batch ends one of the actor's episodes
        st.episodes += 1
        st.boundaries.append(Boundary(st.episodes, st.owed_total, st.ingested, st.collisions_cum))


def replay(st: LearnerRun, records: list, cut: int | None) -> list[str]:
    """The log beyond the cut: batches in replay at the cut refill the buffer; those
    taken but not yet counted wait for the counter's ack again. Returns the batches
    skipped as out of order, as 'actor@seq'."""
    st.resumed_from = cut
    skipped = []
    for rec in records:
        rows = columns(rec.keys, rec.n)
        if not st.received.take(rec.actor, rec.seq, rec.n).took:
            skipped.append(f"{rec.actor}@{rec.seq}")
            continue
        # Newer than any version an actor acted with: the lags stay >= 0.
        st.version = max(st.version, int(rows["policy_version"]))
        if rec.seq < st.ingested_pos.get(rec.actor, 0):  # in replay at the cut
            st.buffer.add(rows["obs"], rows["act"], rows["rew"], rows["next_obs"], rows["done"])
        else:  # taken, not yet counted at the cut: waits for the counter's ack again
            st.held[rec.actor].append(Transitions(st.run, rec.actor, rec.seq, **rows))
    return skipped


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
