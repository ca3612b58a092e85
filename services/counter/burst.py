"""What a burst of batches adds to a run's counts, decided before anything is counted.

The exactly-once rule (the run's `ReceiveCursor`: its actors, whole batches, as the
learner's) runs batch by batch in arrival order on a staging copy of the run's cursor;
what one actor has taken in a burst is one contiguous range (each taken batch starts
where the last ended), so it becomes one log record.
`commit` then hashes the rows, logs them, counts them and only then swaps the staged
cursor in; the service acknowledges after it: an acknowledged count is always on disk.

Per-batch costs (the hash call, a log write, a table lock, above all an ack encoded and
put on the bus) dominate small batches, so batches wait in a burst (`Pending`) and a
burst of them, as a flood of 20-row episodes arrives, shares one of each per run.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from services.counter.state import RunState
from shared.net.protocol import ReceiveCursor

Batch = tuple[str, int, np.ndarray, np.ndarray]  # actor, seq, obs, act
# Taken batches wait in a burst until the inbox is empty, this many rows are buffered,
# or the oldest has waited this long: whichever comes first ends the burst.
BURST_MAX_ROWS = 512
BURST_MAX_WAIT_S = 0.002


@dataclass
class Pending:
    """Checked batches not taken yet, in arrival order, per run."""

    max_rows: int = BURST_MAX_ROWS
    max_wait_s: float = BURST_MAX_WAIT_S
    runs: dict[str, tuple[RunState, list[Batch]]] = field(default_factory=dict)
    rows: int = 0
    since: float = 0.0  # when the oldest batch arrived

    def add(self, run: str, st: RunState, batch: Batch, now: float) -> bool:
        """Buffer a batch; True when the burst is full and must be taken now."""
        if not self.runs:
            self.since = now
        self.runs.setdefault(run, (st, []))[1].append(batch)
        self.rows += len(batch[2])
        return self.rows >= self.max_rows

    def due(self, now: float) -> bool:
        """The oldest batch has waited long enough (an inbox that never empties)."""
        return bool(self.runs) and now - self.since >= self.max_wait_s

    def take(self) -> dict[str, tuple[RunState, list[Batch]]]:
        """The burst's batches by run (first arrival order), the buffer emptied."""
        runs, self.runs, self.rows = self.runs, {}, 0
        return runs


@dataclass
class Burst:
    staged: ReceiveCursor  # the run's cursor once the burst is taken
    segments: list[tuple[str, int, int]]  # per actor taking rows: (actor, first seq, rows)
    obs: np.ndarray | None  # the rows taken, in segment order (None: nothing taken)
    act: np.ndarray | None

    @property
    def rows(self) -> int:
        return sum(rows for _, _, rows in self.segments)


def plan(cursor: ReceiveCursor, batches: list[Batch]) -> Burst:
    """The rows of `batches` that are new (an overlap's new tail too, for a cursor that
    takes one), by actor."""
    staged = cursor.copy()
    taken: dict[str, tuple[int, list[np.ndarray], list[np.ndarray]]] = {}
    for actor, seq, obs, act in batches:
        start = staged.expected(actor)
        d = staged.take(actor, seq, len(obs))
        if not d.took:
            continue
        if d.skip:
            obs, act = obs[d.skip :], act[d.skip :]
        if actor not in taken:
            taken[actor] = (start, [], [])
        taken[actor][1].append(obs)
        taken[actor][2].append(act)
    if not taken:
        return Burst(staged, [], None, None)
    segments = [(a, start, staged.expected(a) - start) for a, (start, _, _) in taken.items()]
    obs_all = [o for _, parts, _ in taken.values() for o in parts]
    act_all = [a for _, _, parts in taken.values() for a in parts]
    obs = obs_all[0] if len(obs_all) == 1 else np.concatenate(obs_all)
    act = act_all[0] if len(act_all) == 1 else np.concatenate(act_all)
    return Burst(staged, segments, obs, act)


def commit(
    st: RunState, plan: Burst, lock: threading.RLock, step_aside: Callable[[], None]
) -> None:
    """Hash, log and count what `plan` took, the staged cursor swapped in only once the
    rows are logged; `step_aside` between the steps lets bonus queries go first."""
    if plan.obs is None or plan.act is None:
        with lock:
            st.cursor = plan.staged  # only the duplicate/gap tallies changed
        return
    step_aside()
    keys = st.explorer.keys(plan.obs, plan.act)  # no lock: hashers are read-only
    step_aside()
    records, pos = [], 0
    for actor, start, rows in plan.segments:
        records.append((actor, start, rows, [k[pos : pos + rows] for k in keys]))
        pos += rows
    st.wal.append_many(records)  # logged before counted and acked
    step_aside()
    with lock:
        for table, k in zip(st.explorer.tables, keys):
            table.increment(k)
        st.cursor = plan.staged
        st.counted += pos
    st.dirty = True
