"""Run control from outside the services: find free services, start, follow, stop.

Used by `macb start` / `macb stop` and by the API service. Services are found by
querying `macb/info/**` (each service answers with its id, role and current run);
a run is assigned one free learner, one counter (the counter serves many runs), one
free evaluator and `actors` free actors, on the learner's node where they can be
(`assign_services`: each service's info names its node).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from shared.config import TrainConfig, actors_error
from shared.net import bus as keys
from shared.net.bus import Bus
from shared.net.info import ServiceInfo
from shared.net.messages import Assignment, History, Metrics, Start, Status, Stop, same_attempt
from shared.net.monitor import (
    Decision,
    Graces,
    LostStart,
    RunMonitor,
    RunVerdict,
    live_peer,
    peer_grace_s,
    start_lost,
)
from shared.net.wire import WireError, decode, encode

log = logging.getLogger("macb.control")
# `start_run` starts a run once, as attempt 1: numbered, so that a service that has let it
# go ignores its start sent again for another that missed it (`start_lost`).
ATTEMPT = 1


class NoFreeServices(RuntimeError):
    """Not enough free services for a run right now (it can wait in a queue)."""


def new_run_id() -> str:
    return time.strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6]


def discover(bus: Bus, timeout: float = 1.0) -> list[dict[str, Any]]:
    """Every live service's info (id, role, run, rejects, ...)."""
    infos = []
    for raw in bus.get(keys.k_info("*", "*"), timeout=timeout):
        try:
            info = json.loads(raw)
        except ValueError:
            continue
        if ServiceInfo.from_json(info) is not None:  # (the reply's map: its readers' own keys)
            infos.append(info)
    return sorted(infos, key=lambda i: (i["role"], i["id"]))


def assign_services(infos: list[dict[str, Any]], actors: int) -> Assignment:
    """A free learner, evaluator and `actors` actors of `infos`, and a counter (busy or
    not), kept on one node where they can be; NoFreeServices says what is missing.

    The rule (`node`: the node a service's info names, `shared.settings.node_name`):
    the learner is the first free one whose node also has a free evaluator and enough
    free actors (else the first free one); the counter is the first on the learner's
    node (else the first); the evaluator and the actors are the first free ones on the
    learner's node, then the others. So a run's lockstep round trips (act requests, the
    counter's acks, bonus queries) stay on one node, and one counter still serves every
    run of a one-node cluster. Services that name no node (older ones) are on no node:
    with none named, or all on one, the first of each is taken, as before the rule.
    """

    def node(i: dict[str, Any]) -> str | None:
        return n if isinstance(n := i.get("node"), str) else None

    def free(role: str) -> list[dict[str, Any]]:
        return [i for i in infos if i["role"] == role and not i.get("run")]

    counters = [i for i in infos if i["role"] == "counter"]
    learners, evaluators, free_actors = free("learner"), free("evaluator"), free("actor")
    missing = []
    if not counters:
        missing.append("counter")
    if not learners:
        missing.append("learner")
    if not evaluators:
        missing.append("evaluator")
    if len(free_actors) < actors:
        missing.append(f"{actors - len(free_actors)} actor(s)")
    if missing:
        raise NoFreeServices("no free " + ", ".join(missing))

    def near(pool: list[dict[str, Any]], where: str | None) -> list[str]:
        """`pool`'s ids, those on `where` first (each side in its order)."""
        return [i["id"] for i in sorted(pool, key=lambda i: node(i) != where)]

    def whole(learner: dict[str, Any]) -> bool:
        where = node(learner)
        return any(node(e) == where for e in evaluators) and (
            sum(node(a) == where for a in free_actors) >= actors
        )

    learner = next((i for i in learners if whole(i)), learners[0])
    where = node(learner)
    return Assignment(
        learner=learner["id"],
        actors=tuple(near(free_actors, where)[:actors]),
        counter=near(counters, where)[0],
        evaluator=near(evaluators, where)[0],
    )


def start_group(
    bus: Bus,
    configs: list[TrainConfig],
    runs: list[str] | None = None,
    wait_for_services: float = 30.0,
) -> list[RunWatch]:
    """Start `configs` as one run group (one learner, actor and evaluator serve them all,
    `interleave: lockstep`); one watch per run, each run with its own id and rows."""
    from shared.groups import group_error

    if why := group_error(configs, 1):
        raise ValueError(why)
    runs = runs or [new_run_id() + f"-{r}" for r in range(len(configs))]
    if len(runs) != len(configs) or len(set(runs)) != len(runs):
        raise ValueError(f"{len(configs)} runs need {len(configs)} distinct ids, got {runs}")
    deadline = time.monotonic() + wait_for_services
    while True:
        try:
            assign = dataclasses.replace(assign_services(discover(bus), 1), group=tuple(runs))
            break
        except NoFreeServices:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    watches = []
    for run, config in zip(runs, configs):
        watch = RunWatch(run, assign, episodes=config.episodes)
        watch.attach(bus)
        watches.append(watch)
    for run, config in zip(runs, configs):
        send_start(bus, run, config, assign)
    return watches


def history_rows(
    bus: Bus, run: str, timeout: float = 2.0, attempt: int | None = None
) -> list[dict[str, Any]]:
    """Every evaluation row the run's evaluator has published (its history queryable),
    in order, of the run's `attempt` (an ended attempt's evaluator may answer too; None:
    any); [] when no evaluator answers. Rows without an integer episode are left out."""
    for raw in bus.get(keys.k_history(run, "eval"), timeout=timeout):
        try:
            msg = decode(raw, History)
        except WireError:
            continue
        if msg.run == run and same_attempt(msg.attempt, attempt):
            return [
                r for r in msg.rows if isinstance(r, dict) and isinstance(r.get("episode"), int)
            ]
    return []


def send_start(
    bus: Bus, run: str, config: TrainConfig, assign: Assignment, attempt: int | None = None
) -> None:
    """Start `run` on `assign` as its `attempt` (None: a starter that never retries)."""
    start = Start(run, config=config.model_dump(mode="json"), assign=assign, attempt=attempt)
    bus.put(keys.k_control("start"), encode(start))


def send_stop(bus: Bus, run: str, reason: str = "stopped by user") -> None:
    bus.put(keys.k_control("stop"), encode(Stop(run, reason=reason)))


UNSERVED_CHECK_S = 3.0  # how often a watch asks who serves its run (as the API does)


@dataclass
class RunWatch:
    """Collects a run's metric rows and service states from the bus as they arrive, and
    ends the run by the API's own rule (`shared.net.monitor.RunMonitor`): its services'
    reports, its services' liveliness, the graces for what does not come, and the end
    of a run no service serves any more (asked every `check_s`; `episodes` says
    whether its last point was in)."""

    run: str
    assign: Assignment
    episodes: int = 0
    check_s: float = UNSERVED_CHECK_S
    rows: list[dict[str, Any]] = field(default_factory=list)
    latest: dict[str, dict[str, Any]] = field(default_factory=dict)  # source -> last data
    changed: threading.Condition = field(default_factory=threading.Condition)
    on_row: Callable[[dict[str, Any]], None] | None = None
    graces: Graces = field(default_factory=lambda: Graces(peer_s=peer_grace_s()))
    _episodes: set[Any] = field(default_factory=set)  # of the rows kept
    _bus: Bus | None = None
    _final: Decision | None = None  # once a run is over, it stays so
    _alive: set[tuple[str, str]] = field(default_factory=set)  # (role, id) with a token
    _checked: float = 0.0  # when who serves the run was last asked
    config: TrainConfig | None = None  # its start's, sent again to a service that missed it
    _lost_start: LostStart = field(default_factory=LostStart)

    def __post_init__(self) -> None:
        self.monitor = RunMonitor(
            self.assign, time.monotonic(), self.graces, episodes=self.episodes, watcher="macb start"
        )
        self._checked = self.monitor.started

    @property
    def states(self) -> dict[str, dict[str, Any]]:
        return self.monitor.states

    def attach(self, bus: Bus) -> None:
        self._bus = bus
        bus.subscribe(keys.k_metrics(self.run, "**"), self._on_metrics)
        bus.subscribe(keys.k_status(self.run, "*"), self._on_status)
        bus.watch_liveliness(keys.k_live("*", "*"), self._on_live)

    def _on_metrics(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, Metrics)
        except WireError:
            return
        with self.changed:
            self.latest[msg.source] = msg.data
            if msg.source == "eval":
                self._add_row(msg.data)
            self.changed.notify_all()

    def _add_row(self, row: dict[str, Any]) -> None:
        # Rows come at least once: an evaluation point the learner sent again (it
        # restarted, or saw no row) is published again. One row per episode is kept.
        episode = row.get("episode")
        if episode in self._episodes:
            return
        self._episodes.add(episode)
        self.rows.append(row)
        self.monitor.points_seen(1, episode if isinstance(episode, int) else None)
        if self.on_row:
            self.on_row(row)

    def _on_status(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, Status)
        except WireError:
            return
        with self.changed:
            self.monitor.status(msg.service, msg.state, msg.fields(), time.monotonic())
            self.changed.notify_all()

    def _on_live(self, key: str, up: bool) -> None:
        if (peer := live_peer(key)) is None:
            return
        with self.changed:
            if up:
                self._alive.add(peer)
            else:
                self._alive.discard(peer)
            self.monitor.peer(*peer, up, time.monotonic())
            self.changed.notify_all()

    def _fill_gaps(self) -> None:
        """Ask the evaluator for every row it published (some were lost on the way)."""
        if self._bus is None:
            return
        rows = history_rows(self._bus, self.run)
        with self.changed:
            for row in rows:
                self._add_row(row)

    def _unserved(self) -> Decision | None:
        """Every `check_s`: the run's end if no service serves it any more (they
        restarted without it, or it ended unseen), by the API's rule."""
        now = time.monotonic()
        if self._bus is None or now - self._checked < self.check_s:
            return None
        self._checked = now
        infos = {i["id"]: i for i in discover(self._bus)}  # (a query: not under the lock)
        with self.changed:
            g = self.graces
            now = time.monotonic()
            ending = self.monitor.unserved(
                self.run, infos, self._alive, now, g.settle_s, g.unserved_s(self.check_s)
            )
            ending = ending or self.monitor.decide(now)  # a learner found gone meanwhile
            said = set(self.monitor.states)  # the services with a status of the run
        lost = None
        if self.config and ending.state == "running" and now - self.monitor.started > g.settle_s:
            lost = start_lost(self.run, self.assign, ATTEMPT, infos, said, self.config.counts)
        if self._lost_start.due(lost is not None, now, g.settle_s) and self.config:
            log.warning("run %s: %s: its start sent again", self.run, lost)
            send_start(self._bus, self.run, self.config, self.assign, ATTEMPT)
        return ending

    def verdict(self) -> RunVerdict:
        """The run's status by its services' reports alone."""
        return self.monitor.verdict()

    def decision(self) -> Decision:
        """What the run is now, by the one rule the API's scheduler also uses."""
        with self.changed:
            if self._final is not None:
                return self._final
            decision = self.monitor.decide(time.monotonic())
        if decision.ask_history:
            self._fill_gaps()  # (a query: not under the lock the bus's callbacks take)
            with self.changed:
                decision = self.monitor.decide(time.monotonic())
        if decision.state == "running":
            decision = self._unserved() or decision
        with self.changed:
            if decision.state != "running" and self._final is None:
                self._final = decision
            return self._final or decision

    def state(self) -> str:
        """running, completed (learner and evaluator done, every point seen, the
        counter's final report in, or what is missing given up on after its grace),
        stopped or failed (a service's report, a service gone past its grace, or no
        service taking the run)."""
        return self.decision().state

    def failure(self) -> str | None:
        d = self.decision()
        return d.reason if d.state == "failed" else None

    def wait(self, timeout: float | None = None) -> str:
        deadline = None if timeout is None else time.monotonic() + timeout
        while (state := self.state()) == "running":
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                break
            with self.changed:
                self.changed.wait(timeout=0.5 if left is None else min(0.5, left))
        return state


def start_run(
    bus: Bus,
    config: TrainConfig,
    actors: int = 1,
    run: str | None = None,
    wait_for_services: float = 30.0,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> RunWatch:
    """Assign free services (waiting up to `wait_for_services` s), start and watch a run."""
    if why := actors_error(config, actors):
        raise ValueError(why)
    run = run or new_run_id()
    deadline = time.monotonic() + wait_for_services
    while True:
        try:
            assign = assign_services(discover(bus), actors)
            break
        except NoFreeServices:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    watch = RunWatch(run, assign, episodes=config.episodes, on_row=on_row, config=config)
    watch.attach(bus)
    send_start(bus, run, config, assign, ATTEMPT)
    return watch
