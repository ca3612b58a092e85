"""A lockstep actor process against this test playing its learner and counter on a real
router: the learner's answer names the runs it ended, and the actor retires them
before it steps with that answer, whether or not the learner's "completed" status has
come. A session's subscriptions are not delivered in order relative to each other
(docs/architecture.md, "Order on the bus"), so that status may come after the answer:
the actor once published a step of a run already ended (a CI failure of
test_lockstep.py::test_a_cluster_group_goes_on_when_its_rule_ends_one_run)."""

from __future__ import annotations

import queue

import numpy as np

from shared.config import make_config
from shared.envs.tasks import task_spec_for
from shared.net import bus as keys
from shared.net.control import send_start
from shared.net.messages import Ack, Action, ActRequest, Assignment, Status, Transitions
from shared.net.wire import decode, encode
from tests.harness import wait_for, wait_services

EPISODE_LEN = 5
EPISODES = 4
CONFIG = {
    "task": "speaker_listener",
    "algo": "cen-maddpg",
    "explore": "constant",
    "episodes": EPISODES,
    "episode_len": EPISODE_LEN,
    "eval_every": 2,
    "eval_episodes": 2,
    "learning_starts": 5,
    "batch_size": 8,
    "hidden": [16, 16],
    "learner_lanes": 1,
    "interleave": "lockstep",
}
RUNS = ["s0", "s1"]
LEARNER, COUNTER, ACTOR = "learner9", "counter9", "actor0"


def play_learner(bus, ended_at: int, status_s0: bool, bad_first: bool = False) -> dict:
    """Serve the actor's group as its learner and counter: answer each act request with
    zero actions, acknowledge every batch; from step `ended_at` on, the answers name s0
    as ended (its "completed" status sent too if `status_s0`, after the answer). What
    the actor published: per run, the sequence numbers of its transitions and its
    statuses."""
    inbox: queue.Queue = queue.Queue()
    # One subscription for everything: what the actor sent arrives in its order.
    bus.subscribe("macb/run/**", lambda key, payload: inbox.put((key, payload)))
    bus.token(keys.k_live("learner", LEARNER))
    bus.token(keys.k_live("counter", COUNTER))
    configs = [make_config({**CONFIG, "seed": s}) for s in (1, 2)]
    act_dim = task_spec_for(configs[0]).joint_act_dim
    assign = Assignment(
        learner=LEARNER, actors=(ACTOR,), counter=COUNTER, evaluator=None, group=tuple(RUNS)
    )
    for run, config in zip(RUNS, configs):
        send_start(bus, run, config, assign)
    action_pub = bus.publisher(keys.k_action(RUNS[0], ACTOR))
    seen: dict[str, dict] = {r: {"seqs": [], "status": []} for r in RUNS}

    def done() -> bool:
        states = [s["status"][-1].state if s["status"] else None for s in seen.values()]
        return states == ["completed", "completed"]

    while not done():
        key, payload = inbox.get(timeout=60)
        run = keys.run_of(key)
        if "/act/" in key:
            ask = decode(payload, ActRequest)
            if bad_first and ask.seq == ended_at:
                bad_first = False  # a malformed answer first: dropped, counted
                act = np.zeros((2, act_dim), np.float32)
                action_pub(encode(Action(RUNS[0], seq=ask.seq, act=act, ended=["s7"])))
            ended = ["s0"] if ask.seq >= ended_at else []
            act = np.zeros((2, act_dim), np.float32)
            action_pub(encode(Action(RUNS[0], seq=ask.seq, act=act, ended=ended)))
            if status_s0 and ask.seq == ended_at:
                bus.put(
                    keys.k_status("s0", LEARNER), encode(Status("s0", LEARNER, "completed", {}))
                )
        elif "/transitions/" in key:
            batch = decode(payload, Transitions)
            seqs = seen[run]["seqs"]  # (a batch resent, unacked for a second: once)
            seqs.extend(q for q in range(batch.seq, batch.seq + len(batch)) if q >= len(seqs))
            for service, window in ((LEARNER, 1000), (COUNTER, 0)):
                acked = {ACTOR: batch.seq + len(batch)}
                ack = Ack(run, service=service, acked=acked, window=window)
                bus.put(keys.k_ack(run, service), encode(ack))
        elif key == keys.k_status(run, ACTOR):
            seen[run]["status"].append(decode(payload, Status))
    return seen


def check(seen: dict, ended_at: int) -> None:
    total = EPISODES * EPISODE_LEN
    assert seen["s0"]["seqs"] == list(range(ended_at)), "s0 stepped past its end"
    assert seen["s1"]["seqs"] == list(range(total))
    s0, s1 = seen["s0"]["status"][-1], seen["s1"]["status"][-1]
    assert (s0.state, s0.final_seq, s0.detail.get("stopped_early")) == ("completed", ended_at, True)
    assert (s1.state, s1.final_seq) == ("completed", total)


def test_an_answer_naming_a_run_ended_retires_it_before_the_step(cluster, bus):
    """No "completed" status for s0 ever comes: the answers alone end it."""
    cluster.service("actor", ACTOR)
    wait_services(bus, 1)
    check(play_learner(bus, ended_at=2 * EPISODE_LEN, status_s0=False), 2 * EPISODE_LEN)


def test_the_status_after_the_answer_changes_nothing_and_a_bad_answer_is_dropped(cluster, bus):
    """The status after the answer (as Zenoh may deliver it) is late traffic; an answer
    naming a run not of the group is dropped, counted and logged, and the actor goes on."""
    cluster.service("actor", ACTOR)
    wait_services(bus, 1)
    seen = play_learner(bus, ended_at=3 * EPISODE_LEN, status_s0=True, bad_first=True)
    check(seen, 3 * EPISODE_LEN)
    info = wait_for(lambda: _info(bus), timeout=10, what="the actor's info")
    assert info["rejects"].get("action", 0) >= 1, info


def _info(bus) -> dict | None:
    import json

    replies = bus.get(keys.k_info("actor", ACTOR), timeout=2.0)
    return json.loads(replies[0]) if replies else None
