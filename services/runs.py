"""Which runs a service serves, which starts it takes, and the file a restart rejoins from.

A service takes a run when the start's assignment names it and it has room (one run,
or the runs of the group it serves; the counter, many). The runs taken are noted in
`DATA_DIR/services/ID.json` (each with its assignment's `to_wire` map, read back
through `from_wire`) so that the same service started again rejoins them before it
announces itself; so are a group's runs their `early_stop` rule ended while the others
go on (`retired`: not served, but their worlds and update entries still belong to the
group). No bus here: the service calls these and runs its hooks.
"""

from __future__ import annotations

import collections
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.config import ConfigError, TrainConfig, make_config
from shared.net.messages import Assignment, run_id_error
from shared.persist.files import write_json


@dataclass(frozen=True)
class SavedRun:
    """A run noted in the runs file: its id, config (raw and parsed) and assignment."""

    run: str
    config: TrainConfig
    assign: Assignment
    raw: dict
    retired: bool = False  # a group's run its `early_stop` rule ended (ServedRuns.retire)
    attempt: int | None = None  # its start's (Start.attempt)


class ServedRuns:
    """The runs served now (`active`, in the order taken), the assignment they came with,
    the last runs let go (their late traffic is expected), and the runs file."""

    def __init__(self, max_runs: int, path: Path | None, log: logging.Logger) -> None:
        self.max_runs = max_runs
        self.path = path  # None: nothing is noted (the counter restores its own runs)
        self.log = log
        self.active: dict[str, TrainConfig] = {}
        self.assign: Assignment | None = None  # of the last run taken
        self.finished: collections.deque[str] = collections.deque(maxlen=64)
        # The attempt each run was started as (Start.attempt), stamped on the service's
        # statuses in it: kept for the runs let go too, whose end statuses may follow.
        self.attempts: dict[str, int | None] = {}
        self._joined: dict[str, tuple[dict, Assignment]] = {}  # run -> (raw config, assign)
        # Runs of the group served that their `early_stop` rule ended while the others go
        # on: no longer served, but noted in the file until the group ends, since a
        # restarted learner or actor serves the group with them (their worlds still step).
        self.retired: dict[str, tuple[dict, Assignment]] = {}

    def full(self) -> bool:
        return len(self.active) >= self.max_runs

    def joins_group(self, run: str, assign: Assignment) -> bool:
        """A start for another run of the group served now (a run group: one learner,
        actor and evaluator for all its runs, `assign.group` their ids)."""
        group = assign.group
        return (
            group is not None
            and run in group
            and bool(self.active)
            and self.assign is not None
            and self.assign.group == group
        )

    def refusal(self, key_run: str | None, msg_run: str) -> str | None:
        """Why a per-run message is dropped (its key's run and its own): None if it is
        for a run served now, "" if silently (late traffic of a run let go is expected)."""
        if key_run is None or msg_run != key_run:
            return "run mismatch: key and message name different runs"
        if key_run not in self.active:
            return "" if key_run in self.finished else f"unknown run: {key_run}"
        return None

    def join(
        self,
        run: str,
        config: TrainConfig,
        assign: Assignment,
        raw: dict,
        attempt: int | None = None,
    ) -> None:
        self.active[run] = config
        self.assign = assign
        self._joined[run] = (raw, assign)
        self.attempts[run] = attempt

    def leave(self, run: str) -> None:
        if run in self.active:
            self.finished.append(run)
        self.active.pop(run, None)
        self._joined.pop(run, None)
        self.retired.pop(run, None)
        if not self.active:
            self.retired.clear()  # (the group is over)
        known = {*self.active, *self.retired, *self.finished}
        for gone in [r for r in self.attempts if r not in known]:
            del self.attempts[gone]

    def retire(self, run: str) -> None:
        """A group's run ended by its rule while the others go on: no longer served (its
        late traffic expected), still noted for a restart while the group goes on."""
        joined = self._joined.get(run)
        self.leave(run)
        if joined is not None and self.active:
            self.retired[run] = joined

    def entries(self) -> list[dict[str, Any]]:
        """What the runs file holds: the runs retired from the group served, then the
        runs served, in order, as they were started."""
        out: list[dict[str, Any]] = [
            {"run": run, "config": raw, "assign": assign.to_wire(), "retired": True}
            for run, (raw, assign) in self.retired.items()
        ]
        out += [
            {"run": run, "config": self._joined[run][0], "assign": self._joined[run][1].to_wire()}
            for run in self.active
        ]
        for e in out:  # (no key for a start that named no attempt, as older files)
            if (attempt := self.attempts.get(e["run"])) is not None:
                e["attempt"] = attempt
        return out

    def save(self) -> None:
        """Note the runs served for a restart (the file removed when none)."""
        if self.path is None:
            return
        if not self.active:
            self.path.unlink(missing_ok=True)
            return
        runs = self.entries()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            write_json(self.path, {"runs": runs})
        except OSError as err:  # the runs go on; only a restart cannot rejoin them
            why = "cannot write %s (%s): a restart will not rejoin %s"
            self.log.error(why, self.path, err, runs)

    def _attempt(self, entry: dict) -> int | None:
        """An entry's `attempt`: None if absent (an older file) or not a positive integer
        (logged: the run is still rejoined, its statuses unstamped, as an older peer's)."""
        try:
            return noted_attempt(entry.get("attempt"))
        except ValueError as err:
            self.log.warning("%s: run %s: %s: taken as none", self.path, entry.get("run"), err)
            return None

    def saved(self) -> list[SavedRun]:
        """The runs noted when the process died; none if there is no file, and none if
        it is unreadable, holds no run, a bad config, a bad assignment or a run id no
        start could name (then it is renamed *.refused)."""
        if self.path is None or not self.path.exists():
            return []
        try:
            data = json.loads(self.path.read_text())
            entries = data.get("runs", [data])  # one run, as a file of old versions holds
            runs = [
                SavedRun(
                    e["run"],
                    make_config(e["config"]),
                    Assignment.from_wire(e["assign"]),
                    e["config"],
                    bool(e.get("retired", False)),
                    self._attempt(e),
                )
                for e in entries
            ]
            if all(r.retired for r in runs):
                raise ValueError("no run in it")
            if why := next(filter(None, (run_id_error(r.run) for r in runs)), None):
                raise ValueError(why)  # (a file written by hand: its folders not built)
        except (OSError, ValueError, KeyError, TypeError, ConfigError) as err:
            self.log.error("refusing %s (%s): renamed *.refused; not rejoining", self.path, err)
            self.path.replace(self.path.with_name(self.path.name + ".refused"))
            return []
        return runs


def noted_attempt(value: Any) -> int | None:
    """An attempt as a file notes it (the runs file, the counter's attempt.json): None
    (not noted) or a positive integer; ValueError for anything else."""
    if value is None or (type(value) is int and value > 0):
        return value
    raise ValueError(f"attempt {value!r} is not a positive integer")


class LearnerProcesses:
    """Per run, the learner processes (`Weights.incarnation`) whose weights a service
    took (the newest `kept` runs'), and for each run started since, those of its ended
    attempts: a run queued again under its id has a new learner process, and what the
    ended attempt's learner still sends (or left as the newest kept) is not the new
    attempt's. The actor and the evaluator keep one each."""

    def __init__(self, kept: int = 16) -> None:
        self.kept = kept
        self.took_from: dict[str, set[str]] = {}
        self.ended: dict[str, set[str]] = {}

    def begin(self, runs: list[str]) -> None:
        """`runs` start (or a restart rejoins them): the processes taken from so far
        are their ended attempts'."""
        for run in runs:
            self.ended[run] = set(self.took_from.get(run, ()))
        for run in [r for r in self.ended if r not in self.took_from and r not in runs]:
            del self.ended[run]  # (nothing taken from: nothing to remember)

    def of_ended_attempt(self, run: str, incarnation: str) -> bool:
        return incarnation in self.ended.get(run, ())

    def took(self, run: str, incarnation: str) -> None:
        self.took_from.setdefault(run, set()).add(incarnation)
        while len(self.took_from) > self.kept:  # runs long over
            self.took_from.pop(next(iter(self.took_from)))
