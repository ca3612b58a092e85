"""A service takes a starter's `start` and `stop` in the order they were sent. They
travel on two keys, and Zenoh does not keep order across a session's subscriptions
(docs/architecture.md, "Order on the bus"): with one subscription per key a stop
that overtook its start was ignored (the run not served yet), and the start then
served a run its starter had ended. An evaluator process on a real router, with
pairs of start and stop sent back to back, then one more start."""

from __future__ import annotations

import json

import pytest

from shared.config import make_config
from shared.net import bus as keys
from shared.net.control import send_start, send_stop
from shared.net.messages import Assignment
from tests.harness import wait_for, wait_services

EVALUATOR = "evaluator0"
CONFIG = {
    "task": "spread",
    "episodes": 4,
    "episode_len": 5,
    "eval_every": 2,
    "eval_episodes": 1,
    "hidden": [16, 16],
}
PAIRS = 40


def _info(bus) -> dict | None:
    replies = bus.get(keys.k_info("evaluator", EVALUATOR), timeout=2.0)
    return json.loads(replies[0]) if replies else None


def test_a_stop_sent_after_its_start_is_taken_after_it(cluster, bus):
    cluster.service("evaluator", EVALUATOR)
    wait_services(bus, 1)
    config = make_config(CONFIG)
    assign = Assignment(
        learner="learner9", actors=("actor9",), counter="counter9", evaluator=EVALUATOR
    )
    for i in range(PAIRS):
        send_start(bus, f"r{i}", config, assign)
        send_stop(bus, f"r{i}")
    send_start(bus, "last", config, assign)  # taken once every pair is over
    # With the stop of some pair taken before its start, that run stays served and
    # the last start is refused (or the run served is that pair's, not the last).
    try:
        wait_for(lambda: (_info(bus) or {}).get("runs") == ["last"], 60, what="the last run")
    except TimeoutError:
        pytest.fail(f"a stop overtook its start: serving {(_info(bus) or {}).get('runs')}")
