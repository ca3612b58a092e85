"""Run control from outside the services: find free services, start, follow, stop.

Used by `macb start` / `macb stop` and by the API service. Services are found by
querying `macb/info/**` (each service answers with its id, role and current run);
a run is assigned one free learner, one counter (the counter serves many runs), one
free evaluator and `actors` free actors.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from shared.config import TrainConfig, actors_error
from shared.net import bus as keys
from shared.net.bus import Bus
from shared.net.messages import Metrics, Start, Status, Stop
from shared.net.protocol import RunVerdict, run_verdict
from shared.net.wire import WireError, decode, encode

# How long a finished run waits for the counter's last report (sent after its snapshot).
COUNTER_GRACE_S = 5.0


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
        if isinstance(info, dict) and "id" in info and "role" in info:
            infos.append(info)
    return sorted(infos, key=lambda i: (i["role"], i["id"]))


def assign_services(infos: list[dict[str, Any]], actors: int) -> dict[str, Any]:
    def free(role: str) -> list[str]:
        return [i["id"] for i in infos if i["role"] == role and not i.get("run")]

    counters = [i["id"] for i in infos if i["role"] == "counter"]
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
    return {
        "counter": counters[0],
        "learner": learners[0],
        "evaluator": evaluators[0],
        "actors": free_actors[:actors],
    }


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
            assign = {**assign_services(discover(bus), 1), "group": list(runs)}
            break
        except NoFreeServices:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    watches = []
    for run in runs:
        watch = RunWatch(run, assign)
        watch.attach(bus)
        watches.append(watch)
    for run, config in zip(runs, configs):
        send_start(bus, run, config, assign)
    return watches


def send_start(bus: Bus, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
    bus.put(
        keys.k_control("start"),
        encode(Start(run, config=config.model_dump(mode="json"), assign=assign)),
    )


def send_stop(bus: Bus, run: str, reason: str = "stopped by user") -> None:
    bus.put(keys.k_control("stop"), encode(Stop(run, reason=reason)))


@dataclass
class RunWatch:
    """Collects a run's metric rows and service states from the bus as they arrive."""

    run: str
    assign: dict[str, Any]
    rows: list[dict[str, Any]] = field(default_factory=list)
    states: dict[str, dict[str, Any]] = field(default_factory=dict)
    latest: dict[str, dict[str, Any]] = field(default_factory=dict)  # source -> last data
    changed: threading.Condition = field(default_factory=threading.Condition)
    on_row: Callable[[dict[str, Any]], None] | None = None
    _episodes: set[Any] = field(default_factory=set)  # of the rows kept
    _finishing_since: float | None = None

    def attach(self, bus: Bus) -> None:
        bus.subscribe(keys.k_metrics(self.run, "**"), self._on_metrics)
        bus.subscribe(keys.k_status(self.run, "*"), self._on_status)

    def _on_metrics(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, Metrics)
        except WireError:
            return
        with self.changed:
            self.latest[msg.source] = msg.data
            # Rows come at least once: an evaluation point the learner sent again (it
            # restarted, or saw no row) is published again. One row per episode is kept.
            episode = msg.data.get("episode")
            if msg.source == "eval" and episode not in self._episodes:
                self._episodes.add(episode)
                self.rows.append(msg.data)
                if self.on_row:
                    self.on_row(msg.data)
            self.changed.notify_all()

    def _on_status(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, Status)
        except WireError:
            return
        with self.changed:
            self.states[msg.service] = {"state": msg.state, **msg.detail}
            self.changed.notify_all()

    def verdict(self) -> RunVerdict:
        """The run's status by the one rule the API's scheduler also uses."""
        return run_verdict(self.states, self.assign, len(self.rows))

    def state(self) -> str:
        """running, completed (learner and evaluator done, every point seen, the
        counter's final report in), stopped or failed. Until the evaluator's last rows
        arrive the run is still running; a counter that does not report its end within
        `COUNTER_GRACE_S` (it was down when the learner finished) does not hold it."""
        v = self.verdict()
        if v.state != "finishing":
            self._finishing_since = None
            return v.state
        now = time.monotonic()
        if self._finishing_since is None:
            self._finishing_since = now
        if not v.missing and now - self._finishing_since > COUNTER_GRACE_S:
            return "completed"
        return "running"

    def failure(self) -> str | None:
        v = self.verdict()
        return v.reason if v.state == "failed" else None

    def wait(self, timeout: float | None = None) -> str:
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.changed:
            while self.state() == "running":
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self.changed.wait(timeout=0.5 if left is None else min(0.5, left))
        return self.state()


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
    watch = RunWatch(run, assign, on_row=on_row)
    watch.attach(bus)
    send_start(bus, run, config, assign)
    return watch
