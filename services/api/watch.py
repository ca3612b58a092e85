"""One run as the API's scheduler follows it, with no bus and no store.

`Watch` holds what the scheduler knows of a run it started or re-attached to: its
`RunMonitor` (shared/net/monitor.py: the one rule that ends a run, shared with
`macb start` and the services, including the end of a run no service serves any
more), the latest stats per source and whether they are saved, and the notes a
resumed learner leaves. The scheduler feeds it decoded messages and clock readings and
writes to the store what it returns, so each rule here can be checked in process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from shared.config import COUNTING_EXPLORE
from shared.net.messages import Assignment, Metrics, Status
from shared.net.monitor import Decision, Graces, LostStart, RunMonitor

LIVE_SAVE_S = 1.0  # a running run's latest stats are saved at most this often


def flat_row(data: dict[str, Any]) -> dict[str, Any]:
    """The JSON-safe part of a message's map: string keys, plain finite values."""
    out: dict[str, Any] = {}
    for k, v in data.items():
        if not isinstance(k, str):
            continue
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        elif isinstance(v, list):
            v = [
                x
                for x in v
                if isinstance(x, str | int) or (isinstance(x, float) and math.isfinite(x))
            ]
        elif isinstance(v, dict):
            v = flat_row(v)
        elif not isinstance(v, str | int | float | bool | type(None)):
            continue
        out[k] = v
    return out


@dataclass(frozen=True)
class Ending:
    """A final status to record; `stop`: tell the run's services to stop it."""

    status: str
    reason: str | None
    stop: bool

    @classmethod
    def of(cls, decision: Decision) -> Ending | None:
        """The monitor's decision as a status to record; None while the run goes on."""
        if decision.state == "running":
            return None
        reason = decision.reason or ("failed" if decision.state == "failed" else None)
        return cls(decision.state, reason, decision.stop)


@dataclass
class Watch:
    """What the scheduler holds for one running run."""

    run: str
    assign: Assignment
    monitor: RunMonitor  # the rule that ends it, fed with its events
    live: dict[str, Any] = field(default_factory=dict)
    live_dirty: bool = False
    live_written: float = 0.0
    ended: float | None = None  # monotonic time it reached a final status
    notes: list[str] = field(default_factory=list)  # resumes: kept as the run's reason
    attempt: int | None = None  # the run's `attempts` when started (Start.attempt)
    lost_start: LostStart = field(default_factory=LostStart)  # a service without its start
    counts: bool = True  # its arm counts (its counter matters to its learning)

    @classmethod
    def of(
        cls, run: dict[str, Any], started: float, graces: Graces, stats: tuple[int, int, int]
    ) -> Watch:
        """A watch over a store row; `stats`: its stored points (count, last seq, last
        episode), so a re-attached watch counts on from what the store has. The row's
        assignment is its map, read through `Assignment.from_wire` (WireError if bad)."""
        assign = Assignment.from_wire(run["assign"])
        monitor = RunMonitor(
            assign,
            started,
            graces,
            run.get("services"),
            points=stats[0],
            episodes=int(run["config"].get("episodes", 0)),
            last_episode=stats[2],
        )
        return cls(
            run=run["id"],
            assign=assign,
            monitor=monitor,
            live=dict(run.get("live") or {}),
            attempt=run.get("attempts"),
            counts=run["config"].get("explore") in COUNTING_EXPLORE,
        )

    @property
    def states(self) -> dict[str, dict[str, Any]]:
        return self.monitor.states

    @property
    def points(self) -> int:
        return self.monitor.points

    @property
    def episodes(self) -> int:
        return self.monitor.episodes

    @property
    def last_episode(self) -> int:
        """The last episode among its stored points."""
        return self.monitor.last_episode

    @property
    def unserved_since(self) -> float | None:
        return self.monitor.unserved_since

    def services(self) -> list[tuple[str, str]]:
        return self.monitor.services()

    def holds(self) -> set[str]:
        """The services it keeps from other runs until it ends (not the shared counter)."""
        return self.assign.held()

    def reason(self) -> str | None:
        """What the run's record says while it runs: what it waits for, else its notes."""
        return self.monitor.waiting() or "; ".join(self.notes) or None

    # ------------------------------------------------------------ events
    def metrics(self, msg: Metrics) -> dict[str, Any] | None:
        """Keep a source's latest stats; an evaluation row (with its episode) is returned
        to be stored as a point."""
        data = flat_row(msg.data)
        if msg.source != "eval":
            self.live[msg.source] = data
            self.live_dirty = True
            return None
        if not isinstance(data.get("episode"), int):
            return None
        self.live["eval"] = data
        self.live_dirty = True
        return data

    def status(self, msg: Status, now: float) -> str | None:
        """A service's status into the monitor; a note when it says its learner resumed
        (new notes only: a learner reports its resume in every status). The caller
        has dropped one of another attempt (`same_attempt`)."""
        self.monitor.status(msg.service, msg.state, flat_row(msg.fields()), now)
        if msg.service != self.assign.learner or msg.resumed is None:
            return None
        cut = msg.resumed.from_episode
        where = f"the cut at episode {cut}" if cut is not None else "its log (no cut yet)"
        note = f"learner {msg.service} restarted and resumed from {where}"
        if note in self.notes:
            return None
        self.notes.append(note)
        return note

    def stored(self, rows: list[dict[str, Any]], added: int) -> None:
        """`added` of these evaluation rows were new to the store."""
        if added:
            self.monitor.points_seen(added, max(int(r["episode"]) for r in rows))

    def live_due(self, now: float) -> bool:
        """Unsaved stats to save now: at most every LIVE_SAVE_S, at once when it ended."""
        return self.live_dirty and (now - self.live_written > LIVE_SAVE_S or self.ended is not None)

    def live_saved(self, now: float) -> None:
        self.live_dirty, self.live_written = False, now

    # ------------------------------------------------------------ what the bus shows
    def unobserved_end(self) -> Ending:
        """How a run no service serves any more ended (the monitor's rule)."""
        ending = Ending.of(self.monitor.unobserved_end())
        assert ending is not None
        return ending
