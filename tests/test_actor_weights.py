"""An actor keeps the newest weights of each run apart: with several runs on one bus
(`macb up --slots`), another run's weights, published every episode, once overwrote a
run's first weights, published once before any episode, and its actor waited forever
(tests/test_up.py::test_slots_run_two_runs_at_once_each_exact hung so)."""

from __future__ import annotations

import threading

from services.actor.main import NEWEST_RUNS_KEPT, ActorService
from shared.net import bus as keys


def bare_actor() -> ActorService:
    """Only what the weights callback uses: no bus, no run."""
    actor = ActorService.__new__(ActorService)
    actor._newest = {}
    actor._newest_lock = threading.Lock()
    return actor


def test_another_runs_weights_do_not_replace_this_runs_first_ones():
    actor = bare_actor()
    actor._on_weights(keys.k_weights("run-b", "latest"), b"b version 0")
    for v in range(1, 5):  # run a's learner publishes every episode
        actor._on_weights(keys.k_weights("run-a", "latest"), f"a version {v}".encode())
    assert actor._newest["run-b"] == (keys.k_weights("run-b", "latest"), b"b version 0")
    assert actor._newest["run-a"][1] == b"a version 4"  # newest only


def test_the_runs_kept_are_bounded_oldest_dropped_first():
    actor = bare_actor()
    for r in range(NEWEST_RUNS_KEPT + 3):
        actor._on_weights(keys.k_weights(f"run-{r}", "latest"), b"w")
    actor._on_weights(keys.k_weights("run-3", "latest"), b"newer")  # arrives again: kept
    runs = list(actor._newest)
    assert len(runs) == NEWEST_RUNS_KEPT
    assert "run-0" not in runs and "run-3" in runs and runs[-1] == "run-3"
