"""An actor keeps the newest weights of each run apart: with several runs on one bus
(`macb up --slots`), another run's weights, published every episode, once overwrote a
run's first weights, published once before any episode, and its actor waited forever
(tests/test_up.py::test_slots_run_two_runs_at_once_each_exact hung so). Weights not of
its policy's layout are refused once and the weights acting kept: a wrong agent count
or shape raised in the actor's loop and ended the process, non-finite ones were acted
with."""

from __future__ import annotations

import logging
import threading

import numpy as np
import pytest
import torch

from services.actor.main import NEWEST_RUNS_KEPT, ActorService
from services.actor.outbox import Outbox, run_sender
from services.actor.runs import ActorRuns
from services.inbox import Rejects
from services.runs import LearnerProcesses, ServedRuns
from shared.config import make_config
from shared.core.networks import JointPolicy, actor_weights, weights_error
from shared.envs.tasks import task_spec_for
from shared.net import bus as keys
from shared.net.messages import Assignment, Weights
from shared.net.wire import encode


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


# ------------------------------------------------------------ weights refused as they come
def serving_actor() -> tuple[ActorService, ActorRuns]:
    """An actor serving run r (async, hidden [16, 16]): what loading weights uses."""
    actor = bare_actor()
    actor.log = logging.getLogger("test.actor")
    actor.reject_tally = Rejects()
    actor.served = ServedRuns(1, None, actor.log)
    actor.acted_with = LearnerProcesses()
    cfg = make_config({"task": "speaker_listener", "episodes": 2, "episode_len": 5,
                       "hidden": [16, 16]})  # fmt: skip
    assign = Assignment.from_wire({"learner": "L", "actors": ["a0"]})
    actor.served.join("r", cfg, assign, {})
    box = Outbox("r", "a0", run_sender(cfg, assign), lambda payload: None)
    return actor, ActorRuns.open("a0", [cfg], {"r": box})


def weights_payload(actors: list[dict], version: int) -> bytes:
    return encode(Weights("r", version=version, updates=0, env_steps=0, episodes=0,
                          eval_point=-1, collisions_cum=0, actors=actors, stats={},
                          incarnation="L:1:2"))  # fmt: skip


def trained(st: ActorRuns, seed: int) -> list[dict]:
    """Weights of the run's layout, as its learner would send them."""
    torch.manual_seed(seed)
    return actor_weights(JointPolicy.for_task(st.world.spec, [16, 16]).actors)


def _nan(actors: list[dict]) -> list[dict]:
    actors[1]["net.0.weight"][0, 0] = np.nan
    return actors


@pytest.mark.parametrize(
    "spoil, why",
    [
        (lambda a: a[:1], "weights for 1 agents, the policy has 2"),  # (raised ValueError)
        (lambda a: [*a, a[0]], "weights for 3 agents"),
        (
            lambda a: [a[0], {**a[1], "net.0.weight": a[1]["net.0.weight"][:, :2]}],
            "net.0.weight is",
        ),
        (lambda a: [a[0], {k: v for k, v in a[1].items() if k != "scale"}], "agent 1: parameters"),
        (lambda a: [a[0], {**a[1], "extra": a[1]["scale"]}], "agent 1: parameters"),
        (lambda a: [a[0], {**a[1], "scale": a[1]["scale"].astype(np.float64)}], "float64"),
        (_nan, "agent 1: net.0.weight has non-finite values"),  # (was loaded, acted with)
    ],
)
def test_weights_not_of_the_policys_layout_are_refused_once_and_the_old_ones_kept(spoil, why):
    actor, st = serving_actor()
    good = trained(st, 0)
    actor._on_weights(keys.k_weights("r", "latest"), weights_payload(good, version=0))
    actor.load_newest_weights(st)
    assert st.version == 0
    assert st.policy is not None
    obs = np.ones((1, st.world.spec.joint_obs_dim), np.float32)
    acting = st.policy(obs)
    actor._on_weights(keys.k_weights("r", "latest"), weights_payload(spoil(trained(st, 1)), 1))
    for _ in range(3):  # (the loop's ticks: refused once, not once a tick)
        actor.load_newest_weights(st)
    by_reason, total = actor.reject_tally.counts()
    assert (by_reason, total) == ({"weights": 1}, 1)
    assert st.version == 0 and "r" not in actor._newest
    assert np.array_equal(st.policy(obs), acting)  # the weights acting are kept
    actor._on_weights(keys.k_weights("r", "latest"), weights_payload(trained(st, 2), 2))
    actor.load_newest_weights(st)
    assert st.version == 2  # the next good weights are taken


def test_a_malformed_weights_message_is_counted_once_not_every_tick():
    actor, st = serving_actor()
    actor._on_weights(keys.k_weights("r", "latest"), b"\x00 not msgpack")
    for _ in range(3):
        actor.load_newest_weights(st)
    assert actor.reject_tally.counts() == ({"undecodable payload": 1}, 1)
    assert st.version == -1 and "r" not in actor._newest


def test_weights_error_takes_what_a_learner_sends():
    policy = JointPolicy.for_task(task_spec_for(make_config({"task": "speaker_listener"})), [8])
    assert weights_error(actor_weights(policy.actors), policy.layout) is None
    assert (
        weights_error("no list", policy.layout) == "weights for no list of agents, the policy has 2"
    )
    assert weights_error([[1], {}], policy.layout) is not None


def test_the_newest_weights_are_decoded_once_not_at_every_tick(monkeypatch):
    """The loop looks for new weights every tick: a message already looked at (loaded,
    or not newer) was decoded again each time, a whole policy's arrays per tick."""
    actor, st = serving_actor()
    decoded = []
    real = ActorService.decode_or_why

    def counting(self, key, payload, kind):
        decoded.append(payload)
        return real(self, key, payload, kind)

    monkeypatch.setattr(ActorService, "decode_or_why", counting)
    actor._on_weights(keys.k_weights("r", "latest"), weights_payload(trained(st, 0), 0))
    for _ in range(5):
        actor.load_newest_weights(st)
    assert st.version == 0 and len(decoded) == 1
    actor._on_weights(keys.k_weights("r", "latest"), weights_payload(trained(st, 1), 1))
    for _ in range(5):
        actor.load_newest_weights(st)
    assert st.version == 1 and len(decoded) == 2  # a new arrival is looked at


def test_weights_looked_at_by_a_run_ended_are_looked_at_again_by_the_next():
    """The message looked at belongs to the runs served: a run started again (a retry,
    a restarted actor rejoining) is a new ActorRuns, which looks at the newest message
    again even when it is the very one its predecessor had."""
    actor, st = serving_actor()
    actor._on_weights(keys.k_weights("r", "latest"), weights_payload(trained(st, 0), 3))
    actor.load_newest_weights(st)
    assert st.version == 3
    again = ActorRuns.open("a0", st.cfgs, st.outboxes)
    actor.load_newest_weights(again)
    assert again.version == 3 and again.policy is not None
