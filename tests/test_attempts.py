"""A run's attempts on the bus: a start names which attempt of the run it is (the
API's `attempts`), every status a service publishes in it says so, and a reader of
one attempt drops the statuses of another. A service may answer an ended attempt's
stop after the run's next attempt started (docs/architecture.md, "Order on the bus");
that late answer must not end the new attempt. An evaluator process on a real router,
its learner played by the test; the counter's record of the attempt on disk."""

from __future__ import annotations

import json
import logging
import queue
import threading

from services.counter.runs import Runs
from services.runs import ServedRuns
from shared.config import make_config
from shared.core.networks import weights_as_arrays
from shared.envs.tasks import task_spec_for
from shared.net import bus as keys
from shared.net.control import send_start, send_stop
from shared.net.messages import (
    Assignment,
    Metrics,
    Start,
    Status,
    Weights,
    learner_of,
    new_incarnation,
)
from shared.net.wire import WireError, decode, encode
from shared.run.factories import build_learner
from tests.harness import wait_for, wait_services

EVALUATOR = "evaluator0"
LEARNER = "learner9"
CONFIG = {
    "task": "spread",
    "episodes": 400,
    "episode_len": 5,
    "eval_every": 200,
    "eval_episodes": 1,
    "hidden": [16, 16],
}
ASSIGN = Assignment(learner=LEARNER, actors=("actor9",), counter="counter9", evaluator=EVALUATOR)


class Statuses:
    """Every status the evaluator publishes, in order."""

    def __init__(self, bus) -> None:
        self.got: list[Status] = []
        self.lock = threading.Lock()
        bus.subscribe(keys.k_status("*", EVALUATOR), self._on)

    def _on(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, Status)
        except WireError:
            return
        with self.lock:
            self.got.append(msg)

    def find(self, state: str, attempt: int | None) -> Status | None:
        with self.lock:
            return next((s for s in self.got if (s.state, s.attempt) == (state, attempt)), None)


def first_attempt(cluster, bus, statuses: Statuses):
    """An evaluator process serving attempt 1 of run "r": its config."""
    cluster.service("evaluator", EVALUATOR)
    wait_services(bus, 1)
    config = make_config(CONFIG)
    send_start(bus, "r", config, ASSIGN, attempt=1)
    wait_for(lambda: statuses.find("running", 1), 60, what="attempt 1 running")
    return config


def learner_says(bus, state: str, attempt: int | None, reason: str) -> None:
    msg = Status("r", service=LEARNER, state=state, detail={}, reason=reason, attempt=attempt)
    bus.put(keys.k_status("r", LEARNER), encode(msg))


def test_a_service_stamps_its_attempt_and_a_late_answer_of_another_does_not_end_it(cluster, bus):
    statuses = Statuses(bus)
    config = first_attempt(cluster, bus, statuses)
    send_stop(bus, "r")
    wait_for(lambda: statuses.find("stopped", 1), 30, what="attempt 1 stopped, stamped 1")
    send_start(bus, "r", config, ASSIGN, attempt=2)
    wait_for(lambda: statuses.find("running", 2), 60, what="attempt 2 running")
    runs_file = cluster.data / "services" / f"{EVALUATOR}.json"  # (written after "running")
    wait_for(
        lambda: runs_file.exists() and json.loads(runs_file.read_text())["runs"][0]["attempt"] == 2,
        10,
        what="the runs file noting attempt 2 (a restart rejoins it as that attempt)",
    )
    # The learner's two answers come on one subscription, in the order sent: attempt
    # 1's late "failed" first. Taken, it would end attempt 2 with its reason.
    learner_says(bus, "failed", 1, "the old attempt's")
    learner_says(bus, "failed", 2, "this attempt's")
    ended = wait_for(lambda: statuses.find("stopped", 2), 30, what="attempt 2 ended")
    assert ended.reason == "learner failed: this attempt's", ended
    # Attempt 2's start again (sent for a counter that missed it): over here, ignored.
    send_start(bus, "r", config, ASSIGN, attempt=2)
    wait_for(
        lambda: "run r: start of attempt 2, let go already: ignored" in cluster.log(EVALUATOR),
        30,
        what="the repeated start ignored",
    )
    assert not [s for s in statuses.got if s.attempt == 2 and s.state == "running"][1:]
    # A start it refuses (a bad config) fails as the attempt it named.
    send_bad_start(bus, attempt=3)
    failed = wait_for(lambda: statuses.find("failed", 3), 30, what="attempt 3 refused")
    assert failed.reason.startswith("invalid config")
    assert statuses.find("running", None) is None  # every status named its attempt


def send_bad_start(bus, attempt: int) -> None:
    config = {**make_config(CONFIG).model_dump(mode="json"), "k": -1}
    start = Start("r", config=config, assign=ASSIGN, attempt=attempt)
    bus.put(keys.k_control("start"), encode(start))


def test_a_runs_file_keeps_each_runs_attempt_and_a_bad_one_is_taken_as_none(tmp_path, caplog):
    path = tmp_path / "services" / "s.json"
    served = ServedRuns(1, path, logging.getLogger("t"))
    served.join("r", make_config(CONFIG), ASSIGN, CONFIG, 4)
    served.save()
    (saved,) = ServedRuns(1, path, logging.getLogger("t")).saved()
    assert (saved.run, saved.attempt) == ("r", 4)
    data = json.loads(path.read_text())
    data["runs"][0]["attempt"] = "4"
    path.write_text(json.dumps(data))
    with caplog.at_level(logging.WARNING):
        (saved,) = ServedRuns(1, path, logging.getLogger("t")).saved()
    assert (saved.run, saved.attempt) == ("r", None) and path.exists()  # rejoined, not refused
    assert "attempt '4' is not a positive integer" in caplog.text


def test_the_counter_keeps_a_runs_attempt_on_disk_for_its_restart(tmp_path, caplog):
    runs = Runs(tmp_path, logging.getLogger("t"))
    config = make_config({"task": "spread", "explore": "cen-macb", "k": 16})
    runs.prepare("r", config, ASSIGN, 3)
    runs.prepare("s", config, ASSIGN)  # a starter that names no attempt
    again = Runs(tmp_path, logging.getLogger("t"))
    assert (again.attempt("r"), again.attempt("s"), again.attempt("never")) == (3, None, None)
    (tmp_path / "r" / "attempt.json").write_text('{"attempt": "3"}')
    with caplog.at_level(logging.WARNING):
        assert again.attempt("r") is None
    assert "attempt.json does not read" in caplog.text and "'3'" in caplog.text


def eval_weights(incarnation: str, env_steps: int) -> bytes:
    """Weights for the evaluator's point 2, `env_steps` marking which ones its row is of."""
    config = make_config(CONFIG)
    actors = weights_as_arrays(build_learner(config, task_spec_for(config)).actor_weights())
    msg = Weights("r", 1, 0, env_steps, 2, 2, 0, actors=actors, stats={}, incarnation=incarnation)
    return encode(msg)


def test_the_evaluator_takes_points_only_from_its_attempts_learner(cluster, bus):
    """After a retry, eval weights of the ended attempt's learner process (late: it was
    paused before its stop), or of a learner the run was not assigned, are not the new
    attempt's: its first point is its own learner's. They come on one subscription, in
    the order sent, the stale ones first."""
    rows: queue.Queue = queue.Queue()
    bus.subscribe(keys.k_metrics("r", "eval"), lambda k, p: rows.put(decode(p, Metrics).data))
    statuses = Statuses(bus)
    config = first_attempt(cluster, bus, statuses)
    old = f"{LEARNER}:100:1"
    bus.put(keys.k_weights("r", "eval"), eval_weights(old, 10))
    assert rows.get(timeout=60)["env_steps"] == 10  # attempt 1's point, from its learner
    send_stop(bus, "r")
    wait_for(lambda: statuses.find("stopped", 1), 30, what="attempt 1 stopped")
    send_start(bus, "r", config, ASSIGN, attempt=2)
    wait_for(lambda: statuses.find("running", 2), 60, what="attempt 2 running")
    for incarnation, marker in ((old, 111), ("learner7:300:3", 333), (f"{LEARNER}:100:2", 222)):
        bus.put(keys.k_weights("r", "eval"), eval_weights(incarnation, marker))
    assert rows.get(timeout=60)["env_steps"] == 222
    assert rows.empty() or all(r["env_steps"] == 222 for r in rows.queue)


def test_an_incarnation_names_its_learner_and_an_older_one_names_none():
    made = new_incarnation("learner-a")
    assert learner_of(made) == "learner-a" and made != new_incarnation("learner-a")
    assert learner_of("l") is None and learner_of("") is None  # (an older learner's)
