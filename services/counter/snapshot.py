"""A counter run's durable state: its tables, positions and stats in snapshot.pt
(written atomically, then the log emptied), and the write-ahead log replayed over it
after a restart, exactly once by sequence number. Pure file work over a `RunState`.

The snapshot is built from the pieces a learner checkpoint is (shared/persist/
checkpoint.py): one atomic write, a `torch.save` file of tensors and primitives read
with weights_only=True, the count tables in the checkpoint's form. A snapshot.npz
from before is still read (and replaced by the next snapshot)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import torch

from services.counter.state import RunState
from shared.core.counting import CountTable
from shared.net.protocol import Arrival, ReceiveCursor
from shared.persist.checkpoint import CutError, load_tables, tables_state
from shared.persist.files import atomic_write
from shared.persist.wal import WalRecord

SNAPSHOT_FORMAT = 2  # 1: snapshot.npz, still read
SNAPSHOT, LEGACY = "snapshot.pt", "snapshot.npz"
# A timed snapshot rewrites the whole table and exists to bound what a restart replays:
# so it waits until the log is this share of the snapshot's size ...
SNAPSHOT_LOG_RATIO = 0.25
# ... and, when the log grows that fast anyway (a flood of new keys), the next check
# waits this many times as long as the last snapshots took: at most ~5% of the time.
SNAPSHOT_SPACING = 20.0


def exists(path: Path) -> bool:
    """The run folder holds a snapshot (of either format)."""
    return (path / SNAPSHOT).exists() or (path / LEGACY).exists()


def write(run: str, st: RunState) -> None:
    """Tables + expected + stats into snapshot.pt (atomic replace), then empty the log.

    Runs on the service thread, the only writer of the tables, so reading them
    needs no lock (queries only read too).
    """
    state = {
        "format": SNAPSHOT_FORMAT,
        "kind": "counter",
        "run": run,
        "time": time.time(),
        "expected": st.cursor.positions(),
        "tables": tables_state(st.explorer.tables),
        "stats": {
            "counted": st.counted,
            "duplicates": st.cursor.duplicate_rows,
            "gaps": st.cursor.gaps,
            "run_rejects": st.run_rejects,
            "queries": st.queries,
            "uncounted_rows_queried": st.uncounted_rows_queried,
            "snapshots": st.snapshots + 1,
        },
    }
    atomic_write(st.path / SNAPSHOT, lambda f: torch.save(state, f))
    (st.path / LEGACY).unlink(missing_ok=True)
    st.wal.truncate()
    st.snapshots += 1
    st.dirty = False


def load(st: RunState) -> None:
    """A run's tables, positions and stats from its snapshot (of both formats there,
    the newer by the time it was written); CutError naming the file if it does not
    read or is not this run's."""
    pt, npz = st.path / SNAPSHOT, st.path / LEGACY
    state = _read_pt(pt) if pt.exists() else None
    legacy = _read_npz(npz) if npz.exists() else None
    if legacy is not None and (state is None or legacy[0].get("time", 0) > state.get("time", 0)):
        meta, arrays = legacy
        _legacy_tables(st, meta, arrays, npz)
    elif state is not None:
        meta = state
        load_tables(st.explorer.tables, state["tables"], pt)
    else:
        raise CutError(f"{st.path}: no snapshot")
    stats = meta["stats"]
    st.cursor = ReceiveCursor({str(a): int(s) for a, s in meta["expected"].items()})
    st.cursor.duplicate_rows = int(stats["duplicates"])
    st.cursor.gaps = int(stats["gaps"])
    st.counted = int(stats["counted"])
    st.run_rejects = int(stats.get("run_rejects", 0))
    st.queries = int(stats.get("queries", 0))
    st.uncounted_rows_queried = int(stats.get("uncounted_rows_queried", 0))
    st.snapshots = int(stats.get("snapshots", 0))


def _read_pt(path: Path) -> dict:
    try:
        state = torch.load(path, weights_only=True)
    except Exception as err:
        raise CutError(f"{path}: unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict) or state.get("format") != SNAPSHOT_FORMAT:
        found = state.get("format") if isinstance(state, dict) else None
        raise CutError(f"{path}: snapshot format {found}, this version reads {SNAPSHOT_FORMAT}")
    return state


def _read_npz(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """A snapshot.npz (format 1): its meta map and its arrays."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        return json.loads(bytes(arrays.pop("meta")).decode()), arrays
    except Exception as err:
        raise CutError(f"{path}: unreadable ({type(err).__name__}: {err})") from None


def _legacy_tables(st: RunState, meta: dict, arrays: dict[str, np.ndarray], path: Path) -> None:
    tables = st.explorer.tables
    if len(meta["totals"]) != len(tables):
        raise CutError(f"{path}: {len(meta['totals'])} count tables, the run has {len(tables)}")
    for t, table in enumerate(tables):
        keys, counts = arrays[f"keys{t}"], arrays[f"counts{t}"]
        if keys.ndim != 2 or keys.shape[1] != table.key_bytes:
            raise CutError(f"{path}: table {t} has keys {keys.shape}")
        tables[t] = CountTable.from_arrays(keys, counts, meta["totals"][t])


def replay(run: str, st: RunState, records: list[WalRecord], log: logging.Logger) -> int:
    """Apply logged batches the snapshot does not hold yet (dedup by seq); how many."""
    replayed = 0
    # A scratch cursor: replay must not add to the run's duplicate/gap tallies.
    cursor = ReceiveCursor(st.cursor.positions())
    for rec in records:
        exp = cursor.expected(rec.actor)
        d = cursor.peek(rec.actor, rec.seq, rec.n)
        if d.arrival is Arrival.DUPLICATE:
            continue  # already in the snapshot (killed between snapshot and truncate)
        if d.arrival is Arrival.GAP:
            log.error(
                "run %s: WAL record %s@%d is past expected %d: skipped",
                run,
                rec.actor,
                rec.seq,
                exp,
            )
            continue
        if len(rec.keys) != len(st.explorer.tables):
            have, want = len(rec.keys), len(st.explorer.tables)
            raise ValueError(f"WAL record has {have} tables, run has {want}")
        cursor.take(rec.actor, rec.seq, rec.n)
        for table, keys in zip(st.explorer.tables, rec.keys):
            table.increment(keys[d.skip :])
        st.counted += d.taken
        replayed += 1
    tallies = st.cursor.duplicate_rows, st.cursor.gaps
    st.cursor = cursor
    st.cursor.duplicate_rows, st.cursor.gaps = tallies
    return replayed


def size(st: RunState) -> int:
    """About what a snapshot of the run writes: keys plus an int64 count per key, or a
    sketch's cells."""
    return sum(t.state_bytes() for t in st.explorer.tables)


def due(st: RunState) -> bool:
    """A timed check should snapshot the run: it changed, and its log is big enough."""
    return st.dirty and st.wal.bytes >= SNAPSHOT_LOG_RATIO * size(st)


def next_check(now: float, every_s: float, spent_s: float) -> float:
    """When to check again, `spent_s` having gone into this check's snapshots."""
    return now + max(every_s, SNAPSHOT_SPACING * spent_s)
