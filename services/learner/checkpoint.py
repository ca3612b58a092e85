"""A learner run's checkpoint (a "cut"): written atomically every CHECKPOINT_EVERY_S,
found again after a restart, applied to a fresh `LearnerRun`.

A cut is a learner checkpoint of kind `service` (shared/persist/checkpoint.py, the
schema `macb train`'s cuts and final checkpoint share) and holds everything but the
replay rows, which the write-ahead log holds: networks, optimizers, targets, the update
and episode counters, the sampler's RNG, which logged batches the buffer holds and the
episode boundaries still owed. Pure file work over a `LearnerRun` (no bus), so a resume
is tested in process.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from services.learner.state import Boundary, LearnerRun
from shared.persist import checkpoint
from shared.persist.checkpoint import CutError as CutError  # what `good` raises
from shared.persist.checkpoint import UnreadableCheckpoint
from shared.persist.wal import WriteAheadLog
from shared.settings import settings

# A cut every this many seconds (MACB_LEARNER_CUT_S overrides): what a restart redoes.
CHECKPOINT_EVERY_S = settings().learner_cut_s  # read in the learner's own process
LOG = "transitions.wal"
CUT, PREVIOUS = "checkpoint.pt", "checkpoint.prev.pt"


def due(st: LearnerRun) -> bool:
    """A cut of the run is due."""
    return time.monotonic() - st.last_ckpt > CHECKPOINT_EVERY_S


def write(st: LearnerRun) -> float:
    """A cut of the run: atomic, the previous cut kept. Taken between ticks, so the
    buffer, the counters and the boundaries owed describe one moment. Returns the
    seconds it took."""
    assert st.folder is not None
    st.last_ckpt = time.monotonic()
    if st.log is not None:
        st.log.sync()  # the rows the cut names are on disk before the cut is
    counters = {
        "ingested": st.ingested,
        "episodes": st.episodes,
        "updates": st.learner.updates,
        "expected": st.received.positions(),
        "version": st.version,
        "collisions_cum": st.collisions_cum,
    }
    path = st.folder / CUT
    checkpoint.save(
        path,
        "service",
        st.config.model_dump(mode="json"),
        st.learner.state_dict(),
        counters,
        rng={"sampler": st.rng.bit_generator.state},
        previous=st.folder / PREVIOUS,
        ingested_pos=dict(st.ingested_pos),
        boundaries=[list(b) for b in st.boundaries],
    )
    spent = time.monotonic() - st.last_ckpt
    st.cuts += 1
    st.cut_s += spent
    st.cut_bytes = path.stat().st_size
    return spent


def good(st: LearnerRun, warn: Callable[[str], None]) -> Iterator[tuple[Path, dict[str, Any]]]:
    """The run's good cuts, newest first (none: the log alone, from the initial
    weights). An unreadable cut is renamed `*.refused`, said with `warn`, and the
    previous one is used; a cut of another config or format raises CutError naming
    the field, with nothing renamed or written."""
    assert st.folder is not None
    mine = st.config.model_dump(mode="json")
    for name in (CUT, PREVIOUS):
        path = st.folder / name
        if not path.exists():
            continue
        try:
            state = checkpoint.load(path, "service", mine)
        except UnreadableCheckpoint as err:
            warn(f"refusing cut {err}; trying the one before")
            path.replace(path.with_name(path.name + ".refused"))
            continue
        yield path, state


def apply(st: LearnerRun, state: dict[str, Any]) -> int:
    """A cut's counters, boundaries and sampler into `st` (its learner is loaded
    apart: a group's runs load together); the cut's episode."""
    counters = state["counters"]
    st.ingested = int(counters["ingested"])
    st.episodes = int(counters["episodes"])
    st.version = int(counters["version"])
    st.collisions_cum = int(counters["collisions_cum"])
    st.ingested_pos = {str(a): int(p) for a, p in state["ingested_pos"].items()}
    st.boundaries = collections.deque(Boundary(*map(int, b)) for b in state["boundaries"])
    st.rng.bit_generator.state = state["rng"]["sampler"]
    return st.episodes


def wipe(folder: Path) -> None:
    """An earlier attempt's log and cuts: a start begins afresh."""
    for old in (LOG, CUT, PREVIOUS):
        (folder / old).unlink(missing_ok=True)


def retire(st: LearnerRun) -> None:
    """The run is over (completed or stopped: a retry starts afresh): its log and the
    older cut are no longer needed (the log grows with every transition). The last
    cut stays."""
    if st.folder is None:
        return
    if st.log is not None:
        st.log.close()
        st.log = None
    for name in (LOG, PREVIOUS):
        (st.folder / name).unlink(missing_ok=True)


def open_log(st: LearnerRun) -> list:
    """The run's log opened for appending (`st.log`), and what an earlier process of
    this learner took (a torn last record is cut off: it was never acked)."""
    assert st.folder is not None
    st.log, records = WriteAheadLog.open(st.folder / LOG)
    return records


def restore_all(
    learner: Any, sts: list[LearnerRun], warn: Callable[[str], None]
) -> list[int | None]:
    """`restore` for a run alone (`learner` None: each run's own), `restore_group` for
    a group's runs (`learner`: the group's)."""
    if learner is None:
        return [restore(st, warn) for st in sts]
    return restore_group(learner, sts, warn)


def restore(st: LearnerRun, warn: Callable[[str], None]) -> int | None:
    """The newest good cut into `st`, its learner included; the cut's episode (None:
    no cut, the log alone from the initial weights)."""
    for _, state in good(st, warn):
        st.learner.load_state_dict(state["learner"])
        return apply(st, state)
    return None


def restore_group(
    learner: Any, sts: list[LearnerRun], warn: Callable[[str], None]
) -> list[int | None]:
    """Every run of a group from its cut at the newest update all of them have a cut
    of (a group's cuts are written together; a kill between two runs' files leaves the
    one before for some); each run's cut episode, all None if there is no such update."""
    options = [
        {int(state["counters"]["updates"]): state for _, state in good(st, warn)} for st in sts
    ]
    common = set.intersection(*(set(o) for o in options))
    if not common:
        if any(options):
            warn(f"group {[st.run for st in sts]}: no update all runs have a cut of: the logs")
        return [None] * len(sts)
    states = [o[max(common)] for o in options]
    learner.load_run_state_dicts([s["learner"] for s in states])
    return [apply(st, state) for st, state in zip(sts, states)]


def resumed(st: LearnerRun, cut: int | None, seconds: float) -> dict[str, Any]:
    """What a resume restored (the service's info and its "running" status say it)."""
    return {
        "run": st.run,
        "from_episode": cut,
        "updates": st.learner.updates,
        "replay_rows": len(st.buffer),
        "held_batches": sum(len(h) for h in st.held.values()),
        "seconds": round(seconds, 3),
    }
