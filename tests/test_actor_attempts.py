"""An async actor process against this test playing its learner on a real router: a
run queued again under its id (a retry) acts with its new learner's weights, never
with those its ended attempt left behind. The actor keeps every run's newest weights
from a subscription of its own, since they may come before the start that makes it
serve the run; a new attempt's start usually comes before the new learner's first
weights, and the actor once took the ended attempt's last weights for them and
collected its first episodes with a trained policy."""

from __future__ import annotations

import queue
import time

from shared.config import make_config
from shared.core.networks import weights_as_arrays
from shared.envs.tasks import task_spec_for
from shared.net import bus as keys
from shared.net.control import send_start, send_stop
from shared.net.messages import Ack, Assignment, Status, Transitions, Weights
from shared.net.wire import decode, encode
from shared.run.factories import build_learner
from tests.harness import wait_services

RUN, LEARNER, ACTOR = "retried", "learner9", "actor0"
EPISODES, EPISODE_LEN = 4, 5
CONFIG = {
    "task": "spread",
    "explore": "none",
    "episodes": EPISODES,
    "episode_len": EPISODE_LEN,
    "eval_every": 2,
    "eval_episodes": 1,
    "hidden": [16, 16],
    "learner_lanes": 1,
    "interleave": "async",
}
ASSIGN = Assignment(learner=LEARNER, actors=(ACTOR,), counter="counter9", evaluator=None)


def weights(config, version: int, incarnation: str, attempt: int | None = None) -> bytes:
    learner = build_learner(config, task_spec_for(config))
    actors = weights_as_arrays(learner.actor_weights())
    msg = Weights(
        RUN, version, 0, 0, 0, -1, 0, actors=actors, stats={}, incarnation=incarnation,
        attempt=attempt,
    )  # fmt: skip
    return encode(msg)


def attempt(
    bus,
    inbox: queue.Queue,
    config,
    first: bytes | None,
    later: bytes,
    wait_s: float,
    number: int | None = None,
):
    """One attempt of the run (`number`: its start's): started, `first` weights at once
    (if any), `later` after `wait_s`; every batch acknowledged with credit. The policy
    versions of the batches until the actor completes (or stops, after its first batch,
    when `first` is given)."""
    send_start(bus, RUN, config, ASSIGN, number)
    if first is not None:
        bus.put(keys.k_weights(RUN, "latest"), first)
    versions: list[int] = []
    acked, started, sent_later, last_ack = 0, time.monotonic(), False, 0.0
    deadline = started + 60
    while time.monotonic() < deadline:
        now = time.monotonic()
        if not sent_later and now - started > wait_s:
            bus.put(keys.k_weights(RUN, "latest"), later)
            sent_later = True
        if now - last_ack > 0.2:  # (as a learner repeats its acks: credit to start with)
            ack = Ack(RUN, service=LEARNER, acked={ACTOR: acked}, window=1000)
            bus.put(keys.k_ack(RUN, LEARNER), encode(ack))
            last_ack = now
        try:
            key, payload = inbox.get(timeout=0.1)
        except queue.Empty:
            continue
        if "/transitions/" in key:
            batch = decode(payload, Transitions)
            if batch.seq == acked:
                versions.append(batch.policy_version)
                acked += len(batch)
                last_ack = 0.0
            if first is not None:
                send_stop(bus, RUN, "the first attempt ends")
                first = None
        elif key == keys.k_status(RUN, ACTOR):
            state = decode(payload, Status).state
            if state in ("completed", "stopped"):
                return versions
    raise TimeoutError(f"the actor did not end the attempt: versions so far {versions}")


def test_a_retried_run_acts_with_its_new_learners_weights(cluster, bus):
    cluster.service("actor", ACTOR)
    wait_services(bus, 1)
    inbox: queue.Queue = queue.Queue()
    bus.subscribe(f"macb/run/{RUN}/**", lambda key, payload: inbox.put((key, payload)))
    config = make_config({**CONFIG, "seed": 1})
    old, new = weights(config, 7, "learner9:1:1"), weights(config, 0, "learner9:2:2")
    assert attempt(bus, inbox, config, first=old, later=old, wait_s=0.0)[0] == 7
    # The new attempt's learner is slow to open: its first weights come a second late.
    versions = attempt(bus, inbox, config, first=None, later=new, wait_s=1.0)
    assert versions == [0] * EPISODES, "the retried run acted with the ended attempt's weights"


def test_an_actor_that_did_not_serve_the_ended_attempt_does_not_take_its_weights(cluster, bus):
    """A retry given to another actor (`macb up --slots`): it kept the run's newest
    weights, the ended attempt's, from its subscription to every run's, without ever
    acting with them. They name attempt 1; it serves attempt 2 and waits for its own."""
    cluster.service("actor", ACTOR)
    wait_services(bus, 1)
    inbox: queue.Queue = queue.Queue()
    bus.subscribe(f"macb/run/{RUN}/**", lambda key, payload: inbox.put((key, payload)))
    config = make_config({**CONFIG, "seed": 1})
    bus.put(keys.k_weights(RUN, "latest"), weights(config, 7, "learner9:1:1", attempt=1))
    # (Its start comes on another subscription; the new weights a second after it, so
    # the old ones are the newest it holds when it starts, whichever it heard first.)
    time.sleep(0.3)
    new = weights(config, 0, "learner9:2:2", attempt=2)
    versions = attempt(bus, inbox, config, first=None, later=new, wait_s=1.0, number=2)
    assert versions == [0] * EPISODES, "the retry acted with the ended attempt's weights"
