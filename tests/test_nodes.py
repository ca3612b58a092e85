"""Counters per node: every service names its node in its info, and the scheduler gives a
run the counter (and the evaluator and actors) on its learner's node, so the lockstep
round trips stay on one node; one counter still serves a one-node cluster.

The rule as pure logic (`shared.net.control.assign_services`), the node a service names
(`shared.settings.node_name`), and real processes on loopback: two counters announced
on different nodes, a learner on node B, a run submitted over REST served by node B's
counter.
"""

from __future__ import annotations

import httpx
import pytest

from shared.net.control import NoFreeServices, assign_services
from shared.net.info import ServiceInfo
from shared.settings import node_name
from tests.harness import TINY, Cluster, assert_exact, wait_for


def svc(sid: str, role: str, node: str | None = None, run: str | None = None) -> dict:
    """A service's info as `discover` returns it (sorted there by role, then id)."""
    return ServiceInfo(sid, role, run=run, node=node).to_json()


def infos(*services: dict) -> list[dict]:
    return sorted(services, key=lambda i: (i["role"], i["id"]))


def test_a_run_gets_the_counter_evaluator_and_actors_of_its_learners_node():
    cluster = infos(
        svc("counter-a", "counter", "a"),
        svc("counter-b", "counter", "b"),
        svc("learner-0", "learner", "a", run="busy"),  # node a's slot is taken
        svc("learner-1", "learner", "b"),
        svc("evaluator-0", "evaluator", "a"),
        svc("evaluator-1", "evaluator", "b"),
        svc("actor-0", "actor", "a"),
        svc("actor-1", "actor", "b"),
    )
    got = assign_services(cluster, 1)
    assert (got.learner, got.counter, got.evaluator, got.actors) == (
        "learner-1",
        "counter-b",
        "evaluator-1",
        ("actor-1",),
    )


def test_the_learner_is_one_whose_node_can_hold_the_whole_run():
    # learner-0 comes first, but its node has no free actor: learner-1 on b does.
    cluster = infos(
        svc("counter-a", "counter", "a"),
        svc("counter-b", "counter", "b"),
        svc("learner-0", "learner", "a"),
        svc("learner-1", "learner", "b"),
        svc("evaluator-0", "evaluator", "a"),
        svc("evaluator-1", "evaluator", "b"),
        svc("actor-0", "actor", "a", run="busy"),
        svc("actor-1", "actor", "b"),
    )
    got = assign_services(cluster, 1)
    assert (got.learner, got.counter, got.actors) == ("learner-1", "counter-b", ("actor-1",))


def test_what_its_node_lacks_comes_from_another_node():
    # Node b has a learner and two actors but no counter and no evaluator; a run of
    # three actors takes b's two and one of a's.
    cluster = infos(
        svc("counter-a", "counter", "a"),
        svc("learner-1", "learner", "b"),
        svc("evaluator-0", "evaluator", "a"),
        svc("actor-0", "actor", "a"),
        svc("actor-1", "actor", "b"),
        svc("actor-2", "actor", "b"),
    )
    got = assign_services(cluster, 3)
    assert got.counter == "counter-a" and got.evaluator == "evaluator-0"
    assert got.actors == ("actor-1", "actor-2", "actor-0")


def test_one_node_or_no_node_named_takes_the_first_of_each_as_before():
    for node in ("only", None):
        cluster = infos(
            svc("counter", "counter", node),
            svc("counter2", "counter", node),
            svc("learner", "learner", node),
            svc("learner1", "learner", node),
            svc("evaluator", "evaluator", node),
            svc("actor0", "actor", node),
            svc("actor1", "actor", node),
        )
        got = assign_services(cluster, 2)
        assert (got.learner, got.counter, got.evaluator, got.actors) == (
            "learner",
            "counter",
            "evaluator",
            ("actor0", "actor1"),
        )


def test_a_busy_counter_still_serves_and_what_is_missing_is_named():
    cluster = infos(
        svc("counter-b", "counter", "b", run="other"),
        svc("learner-1", "learner", "b"),
        svc("evaluator-1", "evaluator", "b"),
        svc("actor-1", "actor", "b"),
    )
    assert assign_services(cluster, 1).counter == "counter-b"
    with pytest.raises(NoFreeServices, match="no free 1 actor"):
        assign_services(cluster, 2)


def test_the_node_a_service_names(monkeypatch):
    monkeypatch.delenv("MACB_NODE", raising=False)
    monkeypatch.setenv("SLURMD_NODENAME", "cn17")
    assert node_name() == "cn17"  # in a Slurm task: Slurm's name for the node
    monkeypatch.setenv("MACB_NODE", "rack2-n3")
    assert node_name() == "rack2-n3"  # an explicit setting wins
    monkeypatch.delenv("MACB_NODE")
    monkeypatch.delenv("SLURMD_NODENAME")
    import socket

    assert node_name() == socket.gethostname().split(".")[0]
    wire = ServiceInfo("c", "counter", node="cn17").to_json()
    assert wire["node"] == "cn17" and ServiceInfo.from_json(wire).node == "cn17"
    assert ServiceInfo.from_json({"id": "c", "role": "counter", "node": 3}).node is None


def test_two_counters_on_two_nodes_a_learner_on_b_is_counted_by_bs_counter(tmp_path):
    """Real processes on loopback: counters `counter-a` (node a, found first) and
    `counter-b` (node b), a learner, an evaluator and an actor on node b; a run posted
    over REST is served and counted by counter-b, and counter-a never hears of it."""
    with Cluster(tmp_path) as cluster:
        cluster.router()
        for node in ("a", "b"):
            sid = f"counter-{node}"
            args = ("counter", "--id", sid, "--data-dir", str(cluster.data / sid))
            cluster.start(sid, *args, env={"MACB_NODE": node})
        for role, sid in (("learner", "learner"), ("evaluator", "evaluator"), ("actor", "actor0")):
            cluster.service(role, sid, env={"MACB_NODE": "b"})
        cluster.api(answering=6)
        workers = cluster.get("/workers")["workers"]
        assert {w["id"]: w["node"] for w in workers if w["role"] == "counter"} == {
            "counter-a": "a",
            "counter-b": "b",
        }, workers
        exp = httpx.post(f"{cluster.url}/experiments", json=TINY).json()
        (run,) = [r["id"] for r in exp["runs"]]
        wait_for(lambda: cluster.ended(run), timeout=180, interval=0.5, what="the run's end")
        finished = cluster.finished(run)
        assert finished.assign["counter"] == "counter-b", finished.assign
        assert_exact(finished)  # counted == collected == ingested, by counter-b
        assert finished.counter["counted_transitions"] == TINY["episodes"] * 20
        assert not (cluster.data / "counter-a" / "counter" / run).exists()
        assert (cluster.data / "counter-b" / "counter" / run).exists()
