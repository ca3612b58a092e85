"""Whole runs on the real cluster: a router and real service processes on loopback."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest

from services.learner import evaluations
from services.learner.bonus import BonusClient, bus_query
from services.learner.evaluations import EvaluationsInFlight
from shared.config import make_config
from shared.core.replay import Batch
from shared.net import bus as keys
from shared.net.bus import Replies
from shared.net.control import discover, start_run
from shared.net.messages import BonusQuery, BonusReply, Transitions
from shared.net.wire import decode, encode
from tests.harness import SMALL, assert_exact, wait_final_counts, wait_for, wait_services


def info(bus, role, sid):
    replies = bus.get(keys.k_info(role, sid), timeout=2.0)
    return json.loads(replies[0]) if replies else None


@pytest.mark.parametrize(
    ("actors", "options"),
    [
        (1, {}),
        (2, {}),
        # The thesis code's learner-side choices: one minibatch per agent (two bonus
        # rows per update in the tick's query), rounded Cen keys, identical initial weights.
        (1, {"minibatch": "per-agent", "hash_round": 2, "same_init": True}),
    ],
    ids=["1", "2", "1-per-agent"],
)
def test_short_speaker_listener_cen_macb_run_is_exact(cluster, bus, actors, options):
    cluster.services(actors)
    wait_services(bus, 3 + actors)
    config = make_config({**SMALL, **options})
    watch = start_run(bus, config, actors=actors)
    assert watch.wait(timeout=240) == "completed", watch.states
    counter_stats = wait_for(lambda: watch.latest.get("counter"), what="counter stats")
    assert counter_stats
    wait_final_counts(watch, config, timeout=5)
    learner = assert_exact(watch, config).learner
    # Every update priced its minibatches: one per agent with `minibatch: per-agent`.
    draws = config.n_agents if config.minibatch == "per-agent" else 1
    rows = round(learner["bonus_rows_per_query"] * learner["bonus_queries"])
    assert rows == draws * config.batch_size * learner["updates"], learner
    # Each actor acted with the learner's weights, and the rising versions reached the
    # actors. Not every actor: credit follows the learner's receipt of a batch, not its
    # ingestion (held until the counter's ack, which comes on another subscription, each
    # on a thread of its own, in no order with the batches), so on a loaded machine one
    # actor may have every batch acknowledged before version 1 reaches it.
    versions = [watch.states[a]["policy_version"] for a in watch.assign.actors]
    assert min(versions) >= 0 and max(versions) > 1, watch.states
    # Services are free again.
    wait_for(lambda: all(not i.get("run") for i in discover(bus)), timeout=10, what="free")


@pytest.mark.parametrize(
    ("task", "actors"),
    [("speaker_listener", 2), ("spread", 1), ("simple", 1)],
)
def test_short_thesis_profile_run_is_exact(cluster, bus, task, actors):
    """`profile: thesis` in the cluster, on each task: the actors' padded speaker
    observations (22-wide joint, row T4) or comm-free spread ones (row T3) fit the
    learner's and counter's tables since all size from the same config; successes reset
    the world inside the window, each actor warms up at random for its share, the
    learner draws a minibatch per agent, and every count stays exact."""
    cluster.services(actors)
    wait_services(bus, 3 + actors)
    algo = {"simple": "ddpg", "spread": "cen-maddpg"}.get(task, SMALL["algo"])
    # Several actors: the asynchronous interleave (lockstep, the profile's default, is
    # one actor's; tests/test_lockstep.py).
    interleave = "async" if actors > 1 else "lockstep"
    config = make_config(
        {**SMALL, "task": task, "algo": algo, "profile": "thesis", "interleave": interleave}
    )
    assert config.success_terminal and config.warmup == "random"
    watch = start_run(bus, config, actors=actors)
    assert watch.wait(timeout=240) == "completed", watch.states
    wait_final_counts(watch, config)
    assert_exact(watch, config)
    wait_for(lambda: all(not i.get("run") for i in discover(bus)), timeout=10, what="free")


@pytest.mark.slow  # a whole cluster or campaign run: ~35-55 s alone on 2 cores
def test_counter_killed_mid_run_loses_no_count(cluster, bus):
    cluster.services(1)
    wait_services(bus, 4)
    # Long enough that the kill lands mid-run: the counter's stats come once a second, and
    # with these small networks 60 episodes could be counted before the first look.
    episodes = 200
    config = make_config({**SMALL, "episodes": episodes, "eval_every": 10})
    watch = start_run(bus, config, actors=1)
    wait_for(
        lambda: watch.latest.get("counter", {}).get("counted_transitions", 0) >= 300,
        timeout=120,
        what="counting under way",
    )
    cluster.kill("counter")  # SIGKILL by PID
    assert watch.latest["counter"]["counted_transitions"] < episodes * 20, "killed too late"
    time.sleep(1.5)
    cluster.service("counter", name="counter2")
    assert watch.wait(timeout=300) == "completed", watch.states
    wait_for(
        lambda: watch.latest["counter"]["counted_transitions"] == episodes * 20,
        timeout=10,
        what="final counter stats after restart",
    )
    assert watch.latest["counter"]["gaps"] >= 0
    published = watch.states["actor0"]["final_seq"]
    assert watch.latest["counter"]["counted_transitions"] == published == episodes * 20
    assert "restored run" in cluster.log("counter2")


def test_garbage_on_every_key_is_dropped_counted_and_changes_nothing(cluster, bus):
    cluster.services(1)
    wait_services(bus, 4)
    config = make_config(SMALL)
    watch = start_run(bus, config, actors=1)
    run = watch.run
    wait_for(lambda: watch.latest.get("learner"), timeout=60, what="learner running")
    wrong_version = msgpack.packb({"v": 99, "type": "transitions", "run": run})
    other_run = encode(
        Transitions(
            "no-such-run",
            actor="actor0",
            seq=0,
            obs=np.zeros((20, 14), np.float32),
            act=np.zeros((20, 5), np.float32),
            rew=np.zeros(20, np.float32),
            next_obs=np.zeros((20, 14), np.float32),
            done=np.zeros(20, np.float32),
            collisions=np.zeros(20, np.int32),
            policy_version=0,
        )
    )
    bad = [b"\x00garbage\xff", wrong_version, b""]
    for payload in bad:
        bus.put(keys.k_transitions(run, "actor0"), payload)
        bus.put(keys.k_ack(run, "learner"), payload)
        bus.put(keys.k_weights(run, "eval"), payload)
        bus.put(keys.k_weights(run, "latest"), payload)
        bus.put(keys.k_metrics(run, "eval"), payload)  # the learner reads eval rows too
        bus.put(keys.k_control("start"), payload)
        bus.put(keys.k_control("stop"), payload)
        assert bus.get(keys.k_bonus(run), payload, timeout=1.0) == []
    bus.put(keys.k_transitions("no-such-run", "actor0"), other_run)
    assert watch.wait(timeout=240) == "completed", watch.states
    wait_final_counts(watch, config, timeout=5)
    assert_exact(watch, config)
    for role in ("counter", "learner", "evaluator", "actor"):
        sid = "actor0" if role == "actor" else role
        i = info(bus, role, sid)
        assert i is not None, f"{role} is not answering"
        assert i["rejects_total"] >= 3, (role, i["rejects"])
    for name, p in cluster.procs.items():
        assert p.poll() is None, f"{name} died"


# The learner in `make test`; the actor, the same failure path, in test-slow.
@pytest.mark.parametrize("victim", ["learner", pytest.param("actor0", marks=pytest.mark.slow)])
def test_a_dead_learner_or_actor_fails_the_run_and_frees_the_others(cluster, bus, victim):
    cluster.env["MACB_PEER_GRACE_S"] = "5"  # the grace a lost peer gets, not the default's 30 s
    cluster.services(1)
    wait_services(bus, 4)
    watch = start_run(bus, make_config({**SMALL, "episodes": 200}), actors=1)
    wait_for(lambda: watch.latest.get("learner", {}).get("updates", 0) > 50, what="training")
    cluster.kill(victim)
    assert watch.wait(timeout=60) == "failed", watch.states
    assert victim.rstrip("0") in watch.failure() or "learner" in watch.failure()
    survivors = {"learner", "actor0", "evaluator"} - {victim}
    wait_for(
        lambda: all(not i.get("run") for i in discover(bus) if i["id"] in survivors),
        timeout=20,
        what="survivors freed",
    )
    assert {i["id"] for i in discover(bus)} >= survivors | {"counter"}


class _FakeBus:
    """Answers bonus queries from a script: per query, the bonus to reply or None."""

    def __init__(self, answers: list) -> None:
        self.answers, self.asked = list(answers), []

    def get_async(self, key: str, payload: bytes, timeout: float) -> list[bytes]:
        self.asked.append(payload)
        bonus = self.answers.pop(0)
        if bonus is None:
            return []
        return [encode(BonusReply("r1", counts=np.ones_like(bonus), bonus=bonus))]

    @staticmethod
    def collect_all(replies: list[bytes]) -> Replies:
        return Replies(ok=replies)


def test_bonus_client_prices_a_ticks_batches_in_one_query_and_splits_the_answer():
    rng = np.random.default_rng(0)
    batches = [
        Batch(
            obs=rng.normal(size=(4, 3)).astype(np.float32),
            act=rng.normal(size=(4, 2)).astype(np.float32),
            rew=np.zeros(4, np.float32),
            next_obs=np.zeros((4, 3), np.float32),
            done=np.zeros(4, np.float32),
            idx=np.arange(4),
        )
        for _ in range(6)
    ]
    answer = np.repeat(np.arange(6, dtype=np.float32), 4)[:, None] * np.ones(2, np.float32)
    bus = _FakeBus([answer, None, answer[:5]])
    client = BonusClient(bus_query(bus, keys.k_bonus("r1")), print, "r1", "cen-macb", 0.8, 2)
    got = client.bonus_for(batches)
    assert len(bus.asked) == 1  # one query for the whole tick
    sent = decode(bus.asked[0], BonusQuery).obs
    assert np.array_equal(sent, np.concatenate([b.obs for b in batches]))
    assert [g.shape for g in got] == [(4, 2)] * 6
    assert [float(g[0, 0]) for g in got] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]  # in order
    assert client.bonus_for(batches) is None  # a silent counter: unanswered, not failed
    assert (client.unanswered, client.failures) == (1, 0)
    assert client.bonus_for(batches) is None  # a reply of 5 rows for 24: no use
    assert (client.unanswered, client.failures) == (1, 1)
    assert client.queries == 1 and client.rows == 24 and client.wait_s > 0


def test_evaluations_in_flight_from_send_to_the_evaluators_row_or_timeout(monkeypatch):
    # A clock of the test's: on a loaded machine the real one can pass max_s between two
    # lines, and `busy` would be False where the test expects True.
    clock = [100.0]
    monkeypatch.setattr(evaluations, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    evals = EvaluationsInFlight(max_s=0.2)
    assert not evals.busy()  # nothing sent
    evals.sent(5)
    assert evals.busy()
    evals.reported(4)  # an older point's row: 5 is still being evaluated
    assert evals.busy()
    evals.reported(5)
    assert not evals.busy()
    evals.sent(10)
    assert evals.busy()
    clock[0] += 0.19
    assert evals.busy()
    clock[0] += 0.02  # no row within max_s: no longer counted as busy
    assert not evals.busy()
    evals.reported(3)  # late rows never move the mark back
    assert evals.last_reported == 5
