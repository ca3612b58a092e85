"""The runs the counter counts: their folders under `data_dir/counter/`, opened from
snapshot and log, restored at startup, archived when a start cannot resume them.

`Runs` owns the run states and the lock that guards their tables and stats between the
service thread (counting) and Zenoh's threads (queries, info). File work only, no bus:
the service publishes what follows (docs/architecture.md, "The counter's files").
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from pathlib import Path

from services.counter import snapshot
from services.counter.state import RunState
from services.runs import noted_attempt
from shared.config import TrainConfig, make_config
from shared.envs.tasks import task_spec_for
from shared.net.messages import Assignment, WireError, run_id_error, same_attempt
from shared.net.protocol import ReceiveCursor
from shared.persist.checkpoint import folder_config_difference
from shared.persist.files import read_json, write_json
from shared.persist.wal import WriteAheadLog
from shared.run.factories import build_exploration


def keys_held(st: RunState) -> int:
    return sum(len(t) for t in st.explorer.tables)


class Runs:
    """Run id -> its state, under `lock`; which of them were restored from disk."""

    def __init__(self, root: Path, log: logging.Logger) -> None:
        self.root = root
        self.log = log
        self.lock = threading.RLock()  # tables and run states: ingestion vs queries/info
        self.states: dict[str, RunState] = {}
        self.restored: set[str] = set()  # runs resumed from disk, not started here

    def get(self, run: str) -> RunState | None:
        with self.lock:
            return self.states.get(run)

    def items(self) -> list[tuple[str, RunState]]:
        with self.lock:
            return list(self.states.items())

    def prepare(
        self, run: str, config: TrainConfig, assign: Assignment, attempt: int | None = None
    ) -> Path:
        """The run's folder for a start: kept if it holds an unfinished run of the same
        config (resumed; a key the saved config lacks counts as its default, the rule
        of every run folder: `folder_config_difference`) and attempt (either not noted:
        taken as the same, `same_attempt`), else what is there is archived; config,
        assignment (its `to_wire` map) and the start's attempt noted. Another attempt's
        tables must not meet this one's transitions, numbered from 0 again."""
        if why := run_id_error(run):  # (refused at the start already: services/common.py)
            raise ValueError(f"{why}: not a safe directory name")
        path = self.root / run
        if path.exists():
            stopped = (path / "stopped").exists()
            if (path / "config.json").exists():
                diff = folder_config_difference(path, config.model_dump(mode="json"))
            else:
                diff = "no config.json"
            noted = self.attempt(run)
            why = None
            if stopped:
                why = "was stopped"
            elif diff is not None:
                why = f"had another config ({diff})"
            elif not same_attempt(noted, attempt):
                why = f"was attempt {noted}, not {attempt}"
            if why is not None:
                dest = self.archive(path)
                self.log.warning("run %s %s: old state moved to %s", run, why, dest)
        path.mkdir(parents=True, exist_ok=True)
        write_json(path / "config.json", config.model_dump(mode="json"))
        write_json(path / "assign.json", assign.to_wire())
        write_json(path / "attempt.json", {"attempt": attempt})
        return path

    def attempt(self, run: str) -> int | None:
        """The attempt a restored run was started as (`prepare`); None if not noted (an
        older counter's folder, a start that named none) or unreadable (logged)."""
        path = self.root / run / "attempt.json"
        if not path.exists():
            return None
        try:
            return noted_attempt(read_json(path).get("attempt"))
        except (OSError, ValueError, AttributeError) as err:
            why = "run %s: %s does not read (%s): its attempt is not known"
            self.log.warning(why, run, path, err)
            return None

    def open(self, run: str, config: TrainConfig, path: Path) -> tuple[RunState, int]:
        """Build the run's tables, load its snapshot and log; register it. Returns the
        state and how many log records were replayed (then folded into a snapshot)."""
        spec = task_spec_for(config)
        explorer = build_exploration(config, spec)
        wal, records = WriteAheadLog.open(path / "wal.bin")
        st = RunState(
            config=config,
            explorer=explorer,
            obs_dim=spec.joint_obs_dim,
            act_dim=spec.joint_act_dim,
            path=path,
            wal=wal,
        )
        try:
            if snapshot.exists(path):
                snapshot.load(st)
            replayed = snapshot.replay(run, st, records, self.log)
        except Exception:
            wal.close()
            raise
        st.rate_counted = st.counted
        if (path / "assign.json").exists():
            try:  # the learner whose end ends the run, the actors whose batches count
                assign = Assignment.from_wire(read_json(path / "assign.json"))
                st.learner, st.actors = assign.learner, assign.actors
            except WireError as err:
                why = "run %s: %s in %s: its learner and actors are not known"
                self.log.warning(why, run, err, path)
        st.cursor = self._receiving(run, st)
        with self.lock:
            self.states[run] = st
        if replayed:
            snapshot.write(run, st)  # fold the log into a snapshot right away
        return st, replayed

    def _receiving(self, run: str, st: RunState) -> ReceiveCursor:
        """The run's cursor as restored (or new), made the learner's rule: the run's
        actors alone (a batch of another is refused), whole batches only (an overlap
        refused, not taken for its tail), so that every row counted is one the learner
        can take. A position restored for an actor the run no longer names is let go
        (logged): its batches would not be taken."""
        positions = st.cursor.positions()
        if st.actors is not None and (strangers := sorted(set(positions) - set(st.actors))):
            self.log.warning("run %s: positions of %s, not of its actors, let go", run, strangers)
            positions = {a: p for a, p in positions.items() if a in st.actors}
        cursor = ReceiveCursor(positions, actors=st.actors, partial=False)
        cursor.duplicate_rows, cursor.gaps = st.cursor.duplicate_rows, st.cursor.gaps
        return cursor

    def restore_all(self) -> list[tuple[str, TrainConfig, RunState]]:
        """Open every run this counter had not finished (no `stopped` marker); a run
        that cannot be opened is logged and left on disk."""
        restored = []
        for path in sorted(self.root.iterdir()):
            if not path.is_dir() or path.name.startswith(".") or (path / "stopped").exists():
                continue
            if not (path / "config.json").exists():
                continue
            run = path.name
            try:
                config = make_config(read_json(path / "config.json"))
                st, replayed = self.open(run, config, path)
            except Exception:
                self.log.exception("could not restore run %s from %s", run, path)
                continue
            self.restored.add(run)
            restored.append((run, config, st))
            self.log.info(
                "restored run %s: %d counted, %d keys, %d WAL records replayed",
                run,
                st.counted,
                keys_held(st),
                replayed,
            )
        return restored

    def archive(self, path: Path) -> Path:
        archive = self.root / ".archive"
        archive.mkdir(exist_ok=True)
        dest = archive / f"{path.name}.{time.strftime('%Y%m%d-%H%M%S')}.{time.time_ns()}"
        shutil.move(str(path), str(dest))
        return dest

    def mark_stopped(self, run: str, st: RunState, reason: str) -> None:
        """The final snapshot, and the marker that keeps a restart from resuming it."""
        snapshot.write(run, st)
        write_json(st.path / "stopped", {"reason": reason, "time": time.time()})

    def close(self, run: str) -> None:
        """Forget a run: closed first, so a query or burst holding it does nothing more."""
        self.restored.discard(run)
        with self.lock:
            st = self.states.pop(run, None)
            if st is not None:
                st.closed = True
        if st is not None:
            st.wal.close()
