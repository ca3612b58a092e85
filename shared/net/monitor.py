"""Is this run over? The one watcher rule, fed by events, with no bus and no clock.

`run_verdict` judges a run by its services' reports. A watcher also has to judge what
did not come: a service whose liveliness token went away and did not come back
(`PeerGrace`), a counter that stays down, a run no service took, a finished run whose
last points or counter report never arrive, and a run no service serves any more
(its end went unseen: `RunMonitor.unserved`). `RunMonitor` holds those timers for one
run. The API's scheduler (services/api/watch.py, runbook.py, reconcile.py) and
`shared.net.control.RunWatch` (`macb start`) are adapters that feed it the same events
and so end runs by the same rule; a service's own peer grace is the same `PeerGrace`,
and `live_peer` is the one reader of a liveliness key.
"""

from __future__ import annotations

from collections.abc import Container, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from shared.net.messages import Assignment, same_attempt
from shared.settings import Settings, settings

# Services without which a run cannot go on; the counter has a grace of its own (it
# serves many runs and resumes them from disk, so it is waited for longer).
ROLES_THAT_MUST_LIVE = ("learner", "evaluator", "actor")
DEFAULT_PEER_GRACE_S: float = Settings.model_fields["peer_grace_s"].default
LIVE_PREFIX = "macb/live/"  # shared.net.bus.k_live's keys: macb/live/ROLE/ID


def live_peer(key: str) -> tuple[str, str] | None:
    """(role, id) of a liveliness key `macb/live/ROLE/ID`, or None for another key."""
    if not key.startswith(LIVE_PREFIX):
        return None
    parts = key.split("/")
    return (parts[2], parts[3]) if len(parts) == 4 and parts[2] and parts[3] else None


def peer_grace_s() -> float:
    """How long a lost peer may take to come back before its runs are given up
    (`MACB_PEER_GRACE_S`): the same for services, the API and `macb start`."""
    return settings().peer_grace_s


@dataclass(frozen=True)
class RunVerdict:
    """A run's status from its services' reports.

    `finishing`: learner and evaluator have completed but fewer metric points were seen
    than the evaluator says it published (`missing`), or the counter's last report (its
    final count, sent after its snapshot) has not come (`counter_pending`): the watcher
    waits for them (or asks for the points) before it calls the run completed, so a
    completed run's record holds every service's final numbers.
    """

    state: str
    reason: str | None = None
    service: str | None = None  # the service whose report decided a failure or stop
    points_expected: int = 0
    missing: int = 0
    counter_pending: bool = False


def run_verdict(
    states: Mapping[str, Mapping[str, Any]], assign: Assignment, points_seen: int
) -> RunVerdict:
    """One rule for "is this run over": first any failure, then any stop, then completion.

    `states` maps service id -> its last status as one map (`Status.fields`, with
    `state`, maybe `reason`, the evaluator's `points`); `assign` names the run's learner
    and evaluator. Of
    several failures the one that gives a reason is reported (a service that merely
    follows another's failure may report first, without one).
    """
    failed = [(svc, st) for svc, st in states.items() if st.get("state") == "failed"]
    if failed:
        svc, st = sorted(failed, key=lambda f: "reason" not in f[1])[0]
        return RunVerdict("failed", f"{svc}: {st.get('reason', 'failed')}", svc)
    for svc, st in states.items():
        if st.get("state") == "stopped":
            return RunVerdict("stopped", f"{svc}: {st.get('reason', 'stopped')}", svc)
    learner = states.get(assign.learner, {}).get("state")
    evaluator = states.get(assign.evaluator or "", {})
    if learner != "completed" or evaluator.get("state") != "completed":
        return RunVerdict("running")
    expected = int(evaluator.get("points", 0))
    missing = max(0, expected - points_seen)  # the evaluator's status may overtake its rows
    counter = assign.counter
    pending = counter is not None and states.get(counter, {}).get("state") != "completed"
    # a learner's reason for completing: its `early_stop` rule held at a point
    why = states.get(assign.learner, {}).get("reason")
    if missing == 0 and not pending:
        return RunVerdict("completed", why, points_expected=expected)
    return RunVerdict(
        "finishing", why, points_expected=expected, missing=missing, counter_pending=pending
    )


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

    @property
    def settle_s(self) -> float:
        """A run younger than this is left to its start: no service serving it yet is
        not yet a sign that it ended unseen."""
        return self.start_s / 4

    def unserved_s(self, check_s: float) -> float:
        """How long no service may serve a run, looked at every `check_s`, before it
        is judged ended unseen (restarted services take a while to rejoin)."""
        return max(check_s, self.peer_s)


@dataclass(frozen=True)
class Decision:
    """What a watcher does now: `state` running, completed, stopped or failed (with its
    `reason`); `ask_history`: the run is over but points are missing, so ask the
    evaluator for them (once) and decide again."""

    state: str
    reason: str | None = None
    ask_history: bool = False

    @property
    def stop(self) -> bool:
        """The run's services are to be told to stop it (a failed or stopped run frees
        them; a completed one has let them go already)."""
        return self.state in ("failed", "stopped")


def finishing_note(verdict: RunVerdict, watcher: str = "the API") -> str:
    """Why a run completed with something missing, once its grace ran out."""
    notes = []
    if verdict.missing:
        notes.append(
            f"{verdict.missing} of {verdict.points_expected} metric points were "
            f"published while {watcher} was not listening"
        )
    if verdict.counter_pending:
        notes.append("the counter's final report did not come (its count is not recorded)")
    return "; ".join(notes)


def serving(run: str, services: Iterable[tuple[str, str]], infos: Mapping[str, Any]) -> list[str]:
    """The run's services whose info says they serve it. Not the counter: it serves many
    runs and resumes those it had from disk when it restarts, including one whose
    learner is gone for good."""
    return [
        sid
        for role, sid in services
        if role != "counter"
        and sid in infos
        and (infos[sid].get("run") == run or run in (infos[sid].get("runs") or []))
    ]


def start_lost(
    run: str,
    assign: Assignment,
    attempt: int | None,
    infos: Mapping[str, Mapping[str, Any]],
    said: Container[str],
    counts: bool = True,
) -> str | None:
    """Which of the run's services missed its start, and how (None: none did).

    A starter puts a run's start once. A service that died just after the run was
    assigned to it never gets it: restarted, it rejoins only what its runs file (the
    counter: its disk) holds, which may be nothing of the run or, for the counter, an
    ended attempt of it whose stop never reached it. The run's other services then wait
    on it for good (the learner on refused bonus queries, the actors on weights). So,
    while some service of the run serves it: a service that answers (a counter: ready)
    and has said nothing in this attempt (`said`: the ids with a status of it, so one
    that did its part and let the run go is not taken for one that missed it) serves
    the run not at all, or (a counter) holds another attempt of it (either naming none
    is taken as the same). `counts`: the run's arm counts; an arm that counts nothing
    learns without its counter. The start sent again is ignored by the services that
    serve the run or have let that attempt go (services/common.py)."""
    services = [(r, s) for r, s in assign.services() if r != "counter" or counts]
    if not serving(run, services, infos):
        return None  # not under way: starting, or ended (the monitor's to judge)
    for role, sid in services:
        info = infos.get(sid)
        if sid in said or info is None or info.get("role") != role:
            continue  # it got the start; or it does not answer (the peer graces apply)
        if role != "counter":
            if not serving(run, [(role, sid)], infos):
                return f"{role} {sid} does not serve the run"
            continue
        if info.get("ready") is not True:
            continue  # still restoring its tables
        held = (info.get("runs") or {}).get(run)
        if not isinstance(held, Mapping):
            return f"counter {sid} does not hold the run"
        if not same_attempt(held.get("attempt"), attempt):
            return f"counter {sid} holds attempt {held.get('attempt')} of the run, not {attempt}"
    return None


@dataclass
class LostStart:
    """When to send a run's start again, a service of it seen without it (`start_lost`)."""

    since: float | None = None  # first seen so, on the looks in a row up to now
    sent_at: float | None = None  # the start last sent again

    def due(self, lost: bool, now: float, every_s: float) -> bool:
        """Whether to send it now: on two looks in a row (a run ending meanwhile frees
        its learner first, so a second look no longer finds it lost), and at most
        every `every_s` (a counter restoring its tables is slow to answer)."""
        if not lost:
            self.since = None
            return False
        if self.since is None:
            self.since = now
            return False
        if self.sent_at is not None and now - self.sent_at < every_s:
            return False
        self.sent_at = now
        return True


class RunMonitor:
    """One run's watcher rule: its services' reports, points and liveliness in; the
    decision (and what it is waiting for) out. Times are the caller's monotonic clock.

    `episodes` (the run's length) and the last episode among its points judge a run
    whose end went unseen; `watcher` names who watches, in the reasons it gives."""

    def __init__(
        self,
        assign: Assignment,
        started: float,
        graces: Graces,
        states: Mapping[str, Mapping[str, Any]] | None = None,
        points: int = 0,
        episodes: int = 0,
        last_episode: int = 0,
        watcher: str = "the API",
    ) -> None:
        self.assign = assign
        self.started = started
        self.graces = graces
        self.states: dict[str, dict[str, Any]] = {k: dict(v) for k, v in (states or {}).items()}
        self.points = points
        self.episodes = episodes
        self.last_episode = last_episode
        self.watcher = watcher
        self.unserved_since: float | None = None  # first check that found no service
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
        """A service's status in the run. Only the services the run was assigned count:
        a run queued again (an API retry) may start on another learner while the one of
        its ended attempt still answers that attempt's stop, on the same run's key."""
        if service not in {sid for _, sid in self.services()}:
            return
        self.states[service] = {**detail, "state": state}
        if state == "completed":  # its part is done: its token may go (see `peer`), and
            # may have gone already, its loss seen first (statuses and liveliness come
            # on subscriptions of their own, in no order between them)
            self.peers.back(service)
            if service == self.assign.counter:
                self.counter_down = None
        if service == self.assign.evaluator and state == "completed":
            self.evaluator_done = now

    def points_seen(self, n: int = 1, last_episode: int | None = None) -> None:
        """`n` new evaluation points, the latest at `last_episode` if given."""
        self.points += n
        if last_episode is not None:
            self.last_episode = max(self.last_episode, last_episode)

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
            return Decision("completed", v.reason)  # (an early stop's, if any)
        if v.state == "finishing":
            if v.missing and not self.history_asked:
                self.history_asked = True  # points lost on the way: ask for them once
                return Decision("running", ask_history=True)
            done = self.evaluator_done if self.evaluator_done is not None else now
            if now - done > self.graces.completion_s:
                note = finishing_note(v, self.watcher)
                return Decision("completed", "; ".join(filter(None, (v.reason, note))))
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

    # ------------------------------------------------------------ what the bus shows
    def unserved(
        self,
        run: str,
        infos: Mapping[str, Mapping[str, Any]],
        alive: Container[tuple[str, str]],
        now: float,
        settle_s: float,
        wait_s: float,
    ) -> Decision | None:
        """How the run ends that its services no longer serve (None: it goes on), from
        the services' infos (`shared.net.control.discover`, by id) and the liveliness
        tokens alive, looked at now and then.

        A run younger than `settle_s` is left to its start. A learner with neither a
        token nor an info is lost as if its token went away (the peer grace applies).
        A run no service serves for `wait_s` ended unseen: `unobserved_end`."""
        if now - self.started < settle_s:
            return None
        served = bool(serving(run, self.services(), infos))
        learner = self.assign.learner
        if ("learner", learner) not in alive and learner not in infos:
            self.peer("learner", learner, False, now)  # gone unseen: the same grace
        if not self.unserved_for(served, now, wait_s):
            return None
        return self.unobserved_end()

    def unserved_for(self, served: bool, now: float, wait_s: float) -> bool:
        """No service has served it for `wait_s`; the clock starts at the first check
        that finds none."""
        if served:
            self.unserved_since = None
            return False
        if self.unserved_since is None:
            self.unserved_since = now
            return False
        return now - self.unserved_since >= wait_s

    def unobserved_end(self) -> Decision:
        """How a run no service serves any more ended, judged by its points: completed
        with its last point in, else failed."""
        if self.last_episode >= self.episodes and self.episodes > 0:
            return Decision(
                "completed", f"its end was not observed ({self.watcher} was not listening)"
            )
        return Decision(
            "failed",
            "its services no longer serve it and no end was seen (it ended while "
            f"{self.watcher} was not listening); last point stored: episode "
            f"{self.last_episode}",
        )
