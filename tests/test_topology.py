"""Two routers peered over TLS on loopback, as two hosts would be: router `router` with
the counter, the learner and the API; router `router-b` (connecting to the first) with
the actors and the evaluator. Every session signs in with its own credentials and both
routers enforce the ACL, so this is the secure multi-host setup of docs/deploy.md on
one machine. What could fail: traffic not crossing the router link (no run, or lost
transitions), a grant missing for a message that only crosses routers (a denial), a
restarted router not rejoining (services on it never come back).
"""

from __future__ import annotations

import httpx
import pytest

from shared.config import make_config
from shared.net.control import discover, start_run
from tests.harness import (
    SMALL,
    Cluster,
    assert_exact,
    free_port,
    router_stats,
    session,
    wait_final_counts,
    wait_for,
    wait_services,
)


class TwoRouters(Cluster):
    """Router `router` (the cluster's endpoint) with the counter, the learner and the
    API if any; router `router-b` (endpoint `b`), peered with it, with the evaluator
    and the actors."""

    def __init__(self, secrets, tmp_path, actors: int) -> None:
        super().__init__(tmp_path, secrets=secrets)
        self.b = f"tls/127.0.0.1:{free_port()}"
        self.actors = [f"actor{r}" for r in range(actors)]


@pytest.fixture
def two(secrets, tmp_path, request):
    options = {"actors": 2, "api": False, **getattr(request, "param", {})}
    with TwoRouters(secrets, tmp_path, options["actors"]) as cluster:
        cluster.router("router")
        cluster.router("router-b", cluster.b, connect=cluster.endpoint)
        on_b = {sid: cluster.b for sid in ("evaluator", *cluster.actors)}
        cluster.services(len(cluster.actors), connect=on_b)
        if options["api"]:
            cluster.api(answering=None)
        yield cluster


def no_denials(bus) -> None:
    for router in ("router", "router-b"):
        stats = router_stats(bus, router)
        assert stats["acl"] and stats["denied_total"] == 0, stats


@pytest.mark.parametrize("two", [{"actors": 2, "api": True}], indirect=True)
def test_a_run_across_two_routers_is_exact(two):
    """Started from router-b's side, the run's control, transitions, acks, weights and
    bonus queries all cross the router link; the API on the other router sees every
    service; nothing is denied anywhere."""
    config = make_config({**SMALL, "episodes": 30})
    with session(two.secrets, "cli", two.b) as cli:
        wait_services(cli, 6, timeout=90)  # 5 services + the API
        watch = start_run(cli, config, actors=2)
        assert watch.wait(timeout=240) == "completed", watch.states
        wait_final_counts(watch, config)
        assert_exact(watch, config)
        assert set(watch.assign.actors) == set(two.actors)
        workers = httpx.get(f"{two.url}/workers", timeout=10).json()["workers"]
        assert {w["id"] for w in workers} >= {"counter", "learner", "evaluator", *two.actors}
        no_denials(cli)


def test_a_router_restarted_while_the_other_carries_on(two):
    """router-b (actors, evaluator) is killed mid-run and started again on its port a
    second later: router `router` and its counter and learner carry on meanwhile (they
    still answer), router-b's clients reconnect by themselves, the peers that went away
    are back within their grace (MACB_PEER_GRACE_S), and the run completes exactly:
    transitions lost in the outage are resent, none is counted twice."""
    config = make_config({**SMALL, "episodes": 40})
    with session(two.secrets, "cli", two.endpoint) as cli:
        wait_services(cli, 5, timeout=90)
        watch = start_run(cli, config, actors=2)
        wait_for(lambda: watch.rows, timeout=120, what="a first point")
        two.kill("router-b")
        # Router `router` alone: its services still answer, router-b's do not. Asked again
        # until so: a learner busy training on a loaded machine can miss one query's second.
        wait_for(
            lambda: {i["id"] for i in discover(cli)} == {"counter", "learner"},
            timeout=10,
            what="only router `router`'s services answering",
        )
        assert watch.state() == "running", watch.states
        two.router("router-b", two.b, connect=two.endpoint)
        assert watch.wait(timeout=240) == "completed", watch.states
        wait_final_counts(watch, config)
        assert_exact(watch, config, faults="lost")
        no_denials(cli)
