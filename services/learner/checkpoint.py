"""A learner run's checkpoint (a "cut"): written atomically every CHECKPOINT_EVERY_S,
found again after a restart, applied to a fresh `LearnerRun`.

A cut is a learner checkpoint of kind `service` (shared/persist/checkpoint.py, the
schema `macb train`'s cuts and final checkpoint share) and holds everything but the
replay rows, which the write-ahead log holds: networks, optimizers, targets, the update
and episode counters, the sampler's RNG, which logged batches the buffer holds and the
episode boundaries still owed. `Cuts` is a run's cut state (its folder, when and how
long the cuts were) and this module its one writer; a cut's contents come from, and go
back to, the parts that own them (`Intake.restore`, `Sampling.load_rng`,
`Outgoing.restore_version`). Pure file work over a `LearnerRun` (no bus),
so a resume is tested in process.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from shared.net.messages import Resumed
from shared.persist import checkpoint
from shared.persist.checkpoint import CutError as CutError  # what `good` raises
from shared.persist.checkpoint import UnreadableCheckpoint
from shared.persist.files import atomic_write
from shared.settings import settings

if TYPE_CHECKING:
    from services.learner.state import LearnerRun

# A cut every this many seconds (MACB_LEARNER_CUT_S overrides): what a restart redoes.
CHECKPOINT_EVERY_S = settings().learner_cut_s  # read in the learner's own process
LOG = "transitions.wal"
CUT, PREVIOUS = "checkpoint.pt", "checkpoint.prev.pt"
RETIRED = "retired.pt"  # a group's run its rule ended, the others going on


@dataclass
class Cuts:
    """Where a run's cuts go (None: nowhere) and what writing them took."""

    folder: Path | None = None  # DATA_DIR/learner/RUN
    last: float = field(default_factory=time.monotonic)  # when the last cut was taken
    written: int = 0
    seconds: float = 0.0  # wall time spent writing cuts (the log's fsync included)
    size: int = 0  # bytes of the last cut file


def due(st: LearnerRun) -> bool:
    """A cut of the run is due."""
    return time.monotonic() - st.cuts.last > CHECKPOINT_EVERY_S


def write(st: LearnerRun) -> float:
    """A cut of the run: atomic, the previous cut kept. Taken between ticks, so the
    buffer, the counters and the boundaries owed describe one moment. Returns the
    seconds it took."""
    cuts, it = st.cuts, st.intake
    assert cuts.folder is not None
    cuts.last = time.monotonic()
    if it.log is not None:
        it.log.sync()  # the rows the cut names are on disk before the cut is
    counters = {
        "ingested": it.ingested,
        "episodes": it.episodes,
        "updates": st.learner.updates,
        "expected": it.received.positions(),
        "version": st.outgoing.version,
        "collisions_cum": it.collisions_cum,
    }
    path = cuts.folder / CUT
    checkpoint.save(
        path,
        "service",
        st.config.model_dump(mode="json"),
        st.learner.state_dict(),
        counters,
        rng={"sampler": st.sampling.rng.bit_generator.state},
        previous=cuts.folder / PREVIOUS,
        ingested_pos=dict(it.ingested_pos),
        boundaries=[list(b) for b in it.boundaries],
    )
    spent = time.monotonic() - cuts.last
    cuts.written += 1
    cuts.seconds += spent
    cuts.size = path.stat().st_size
    return spent


def good(st: LearnerRun, warn: Callable[[str], None]) -> Iterator[tuple[Path, dict[str, Any]]]:
    """The run's good cuts, newest first (none: the log alone, from the initial
    weights). An unreadable cut is renamed `*.refused`, said with `warn`, and the
    previous one is used; a cut of another config or format raises CutError naming
    the field, with nothing renamed or written."""
    assert st.cuts.folder is not None
    mine = st.config.model_dump(mode="json")
    for name in (CUT, PREVIOUS):
        path = st.cuts.folder / name
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
    st.intake.restore(counters, state["ingested_pos"], state["boundaries"])
    st.outgoing.restore_version(int(counters["version"]))
    st.sampling.load_rng(state["rng"]["sampler"])
    return st.intake.episodes


def wipe(folder: Path) -> None:
    """An earlier attempt's log, cuts and best point: a start begins afresh."""
    for old in (LOG, CUT, PREVIOUS, checkpoint.BEST, RETIRED):
        (folder / old).unlink(missing_ok=True)


def save_retired(folder: Path, arrays: tuple[np.ndarray, ...]) -> None:
    """A group's run retired by its rule (`Serving.retire`): its fixed update arrays,
    for a learner restarted while the others go on (its replay log is gone with it).
    Tensors only, read with torch.load(weights_only=True)."""
    state = {"arrays": [torch.from_numpy(np.ascontiguousarray(a)) for a in arrays]}
    atomic_write(folder / RETIRED, lambda f: torch.save(state, f))


def load_retired(folder: Path) -> tuple[np.ndarray, ...]:
    """What `save_retired` wrote; CutError naming the file if it cannot be read."""
    try:
        state = torch.load(folder / RETIRED, weights_only=True)
        return tuple(t.numpy() for t in state["arrays"])
    except Exception as err:
        raise CutError(f"{folder / RETIRED}: {type(err).__name__}: {err}") from None


def best_so_far(st: LearnerRun) -> float:
    """The success of the point in the run's best.pt (`early_stop`), -1 without one: a
    resumed learner replaces it only with a better point, as the rows it reads again
    from the evaluator are the ones it had read."""
    path = st.cuts.folder / checkpoint.BEST if st.cuts.folder is not None else None
    if path is None or not path.exists():
        return -1.0
    try:
        best = checkpoint.load(path, "best", st.config.model_dump(mode="json"))
    except checkpoint.CutError:  # (unreadable or another config: the next point rewrites it)
        return -1.0
    return float(best["counters"]["success_rate"])


def retire(st: LearnerRun) -> None:
    """The run is over (completed or stopped: a retry starts afresh): its log and the
    older cut are no longer needed (the log grows with every transition). The last
    cut stays."""
    folder = st.cuts.folder
    if folder is None:
        return
    st.intake.close_log()
    for name in (LOG, PREVIOUS):
        (folder / name).unlink(missing_ok=True)


def open_log(st: LearnerRun) -> list:
    """The run's log opened for appending (`Intake.log`), and what an earlier process of
    this learner took (a torn last record is cut off: it was never acked)."""
    assert st.cuts.folder is not None
    return st.intake.open_log(st.cuts.folder / LOG)


def restore(
    learner: Any,
    sts: list[LearnerRun],
    warn: Callable[[str], None],
    slots: tuple[list[int], int] | None = None,
) -> list[int | None]:
    """The runs served (a run alone, or a group's runs) from their cuts at the newest
    update all of them have a cut of (a group's cuts are written together; a kill
    between two runs' files leaves the one before for some), into `learner` (their one
    learner: `load_run_state_dicts`) and each run's state; each run's cut episode, all
    None if there is no such update (the logs alone, from the initial weights). Of two
    cuts of one update, the newer is taken. `slots`: the group members `sts` are, and
    the group's size, when some were retired by their rule (their entries, whose
    weights nothing reads, take the first run's state: one update count for all)."""
    options = []
    for st in sts:
        cuts: dict[int, dict[str, Any]] = {}
        for _, state in good(st, warn):  # newest first
            cuts.setdefault(int(state["counters"]["updates"]), state)
        options.append(cuts)
    common = set.intersection(*(set(o) for o in options))
    if not common:
        if any(options):
            warn(f"runs {[st.run for st in sts]}: no update all have a cut of: the logs")
        return [None] * len(sts)
    states = [o[max(common)] for o in options]
    members = [s["learner"] for s in states]
    if slots is not None:
        at, size = slots
        members = [members[at.index(r)] if r in at else members[0] for r in range(size)]
    learner.load_run_state_dicts(members)
    return [apply(st, state) for st, state in zip(sts, states)]


def resumed(st: LearnerRun, cut: int | None, seconds: float) -> Resumed:
    """What a resume restored (the service's info and its "running" status say it)."""
    return Resumed(
        run=st.run,
        from_episode=cut,
        updates=st.learner.updates,
        replay_rows=len(st.intake.buffer),
        held_batches=sum(len(h) for h in st.intake.held.values()),
        seconds=round(seconds, 3),
    )
