"""Is this run over? One rule for every watcher, fed by events, with no bus and no clock.

`run_verdict` (shared/net/protocol.py) judges a run by its services' reports. A watcher
also has to judge what did not come: a service whose liveliness token went away and
did not come back (`PeerGrace`), a counter that stays down, a run no service took, a
finished run whose last points or counter report never arrive. `RunMonitor` holds those
timers for one run: the API's scheduler, `shared.net.control.RunWatch` (`macb start`)
feed it the same events and so end runs by the same rule; a service's own peer grace
is the same `PeerGrace`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from shared.net.messages import Assignment
from shared.net.protocol import RunVerdict, run_verdict

# Services without which a run cannot go on; the counter has a grace of its own (it
# serves many runs and resumes them from disk, so it is waited for longer).
ROLES_THAT_MUST_LIVE = ("learner", "evaluator", "actor")
DEFAULT_PEER_GRACE_S = 30.0


def peer_grace_s() -> float:
    """How long a lost peer may take to come back before its runs are given up
    (`MACB_PEER_GRACE_S`): the same for services, the API and `macb start`."""
    return float(os.environ.get("MACB_PEER_GRACE_S", DEFAULT_PEER_GRACE_S))


class PeerGrace:
    """Peers whose liveliness token went away, each given `grace_s` to come back."""

    def __init__(self, grace_s: float) -> None:
        self.grace_s = grace_s
        self.down: dict[str, tuple[str, float]] = {}  # peer id -> (role, since)

    def lost(self, role: str, peer: str, now: float) -> bool:
        """The peer's token went away; True if it was not down already."""
        if peer in self.down:
            return False
        self.down[peer] = (role, now)
        return True

    def back(self, peer: str) -> bool:
        """The peer's token came back; True if it had been down."""
        return self.down.pop(peer, None) is not None

    def expired(self, now: float) -> list[tuple[str, str]]:
        """(role, peer) of every peer away for `grace_s` or more (given up: forgotten)."""
        gone = [(role, p) for p, (role, since) in self.down.items() if now - since >= self.grace_s]
        for _, p in gone:
            del self.down[p]
        return gone

    def clear(self) -> None:
        self.down.clear()

    def __contains__(self, peer: object) -> bool:
        return peer in self.down

    def __bool__(self) -> bool:
        return bool(self.down)


@dataclass(frozen=True)
class Graces:
    """How long a watcher waits for what has not come, in seconds."""

    peer_s: float = DEFAULT_PEER_GRACE_S  # a lost learner, evaluator or actor to come back
    counter_s: float = 120.0  # a lost counter to come back
    completion_s: float = 5.0  # the last points and the counter's report after the end
    start_s: float = 60.0  # some service to take the run


@dataclass(frozen=True)
class Decision:
    """What a watcher does now: `state` running, completed, stopped or failed (with its
    `reason`); `ask_history`: the run is over but points are missing, so ask the
    evaluator for them (once) and decide again."""

    state: str
    reason: str | None = None
    ask_history: bool = False


def finishing_note(verdict: RunVerdict) -> str:
    """Why a run completed with something missing, once its grace ran out."""
    notes = []
    if verdict.missing:
        notes.append(
            f"{verdict.missing} of {verdict.points_expected} metric points were "
            "published while the API was not listening"
        )
    if verdict.counter_pending:
        notes.append("the counter's final report did not come (its count is not recorded)")
    return "; ".join(notes)


class RunMonitor:
    """One run's watcher rule: its services' reports, points and liveliness in; the
    decision (and what it is waiting for) out. Times are the caller's monotonic clock."""

    def __init__(
        self,
        assign: Assignment,
        started: float,
        graces: Graces,
        states: Mapping[str, Mapping[str, Any]] | None = None,
        points: int = 0,
    ) -> None:
        self.assign = assign
        self.started = started
        self.graces = graces
        self.states: dict[str, dict[str, Any]] = {k: dict(v) for k, v in (states or {}).items()}
        self.points = points
        self.peers = PeerGrace(graces.peer_s)
        self.counter_down: float | None = None
        self.evaluator_done: float | None = None  # when the evaluator said completed
        self.history_asked = False
        evaluator = self.states.get(str(assign.evaluator), {})
        if evaluator.get("state") == "completed":  # a watcher started after its end
            self.evaluator_done = started

    def services(self) -> list[tuple[str, str]]:
        """(role, id) of every service serving the run."""
        return self.assign.services()

    # ------------------------------------------------------------ events
    def status(self, service: str, state: str, detail: Mapping[str, Any], now: float) -> None:
        self.states[service] = {**detail, "state": state}
        if service == self.assign.evaluator and state == "completed":
            self.evaluator_done = now

    def points_seen(self, n: int = 1) -> None:
        self.points += n

    def peer(self, role: str, sid: str, up: bool, now: float) -> None:
        """A liveliness token of the run's `role` `sid` appeared (`up`) or went away."""
        if (role, sid) not in self.services():
            return
        if up:
            self.peers.back(sid)
            if role == "counter":
                self.counter_down = None
            return
        if self.states.get(sid, {}).get("state") == "completed":
            return  # its part is done (an actor that finished, say)
        if role == "counter":
            if self.counter_down is None:
                self.counter_down = now
        elif role in ROLES_THAT_MUST_LIVE:
            self.peers.lost(role, sid, now)

    def waiting(self) -> str | None:
        """What the run waits for now (a service to come back), or None."""
        if self.counter_down is not None:
            return f"counter {self.assign.counter} is down; waiting for it to return"
        for sid, (role, _) in self.peers.down.items():
            return f"{role} {sid} is down; waiting up to {self.graces.peer_s:g} s for it"
        return None

    # ------------------------------------------------------------ the rule
    def verdict(self) -> RunVerdict:
        return run_verdict(self.states, self.assign, self.points)

    def decide(self, now: float) -> Decision:
        """First the services' reports (failure, stop, completion); then what has not
        come within its grace: the last points, a lost service, any service at all."""
        v = self.verdict()
        if v.state in ("failed", "stopped"):
            return Decision(v.state, v.reason or v.state)
        if v.state == "completed":
            return Decision("completed")
        if v.state == "finishing":
            if v.missing and not self.history_asked:
                self.history_asked = True  # points lost on the way: ask for them once
                return Decision("running", ask_history=True)
            done = self.evaluator_done if self.evaluator_done is not None else now
            if now - done > self.graces.completion_s:
                return Decision("completed", finishing_note(v))
            return Decision("running")
        for role, sid in self.peers.expired(now):
            return Decision(
                "failed",
                f"{role} {sid} died (its liveliness token went away) and did not come back "
                f"within {self.graces.peer_s:g} s",
            )
        if self.counter_down is not None and now - self.counter_down > self.graces.counter_s:
            return Decision("failed", f"counter {self.assign.counter} did not come back")
        if not self.states and now - self.started > self.graces.start_s:
            return Decision("failed", f"no service took the run within {self.graces.start_s:.0f} s")
        return Decision("running")
