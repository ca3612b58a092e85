"""Two routers peered over TLS on loopback, as two hosts would be: router `router` with
the counter, the learner and the API; router `router-b` (connecting to the first) with
the actors and the evaluator. Every session signs in with its own credentials and both
routers enforce the ACL, so this is the secure multi-host setup of docs/deploy.md on
one machine. What could fail: traffic not crossing the router link (no run, or lost
transitions), a grant missing for a message that only crosses routers (a denial), a
restarted router not rejoining (services on it never come back).
"""

from __future__ import annotations

import signal
import time

import httpx
import pytest

from shared.config import make_config
from shared.control import discover, start_run
from tests.conftest import Procs, free_port, wait_for, wait_port
from tests.test_secure_bus import as_user, router_stats, session, wait_final_counts
from tests.test_services_run import SMALL, check_exact


class TwoRouters:
    """The processes of the two-router cluster, each with its own log."""

    def __init__(self, secrets, tmp_path, actors: int = 2, api: bool = False) -> None:
        self.secrets = secrets
        self.a = f"tls/127.0.0.1:{free_port()}"
        self.b = f"tls/127.0.0.1:{free_port()}"
        self.procs = Procs(tmp_path, self.a)
        self.data = str(tmp_path / "data")
        self.actors = [f"actor{r}" for r in range(actors)]
        self.url = f"http://127.0.0.1:{free_port()}"
        self.start_router("router", self.a)
        self.start_router("router-b", self.b, connect=self.a)
        for sid in ("counter", "learner"):
            self.service(sid, self.a)
        for sid in ("evaluator", *self.actors):
            self.service(sid, self.b)
        if api:
            listen = self.url.removeprefix("http://")
            env = as_user(secrets, "api", self.a)
            self.procs.start(
                "api", "api", "--listen-http", listen, "--data-dir", self.data, env=env
            )

    def start_router(self, name: str, listen: str, connect: str | None = None) -> None:
        args = ["router", "--listen", listen] + (["--connect", connect] if connect else [])
        self.procs.start(name, *args, env=as_user(self.secrets, name))
        wait_port(listen)

    def service(self, sid: str, endpoint: str) -> None:
        kind = sid.rstrip("0123456789")
        env = as_user(self.secrets, sid, endpoint)
        self.procs.start(sid, kind, "--id", sid, "--data-dir", self.data, env=env)

    def wait_services(self, bus, n: int, timeout: float = 90) -> None:
        wait_for(lambda: len(discover(bus)) >= n, timeout=timeout, what=f"{n} services")

    def no_denials(self, bus) -> None:
        for router in ("router", "router-b"):
            stats = router_stats(bus, router)
            assert stats["acl"] and stats["denied_total"] == 0, stats


@pytest.fixture
def two(secrets, tmp_path, request):
    cluster = TwoRouters(secrets, tmp_path, **getattr(request, "param", {}))
    yield cluster
    cluster.procs.stop_all()
    for name, p in cluster.procs.procs.items():
        assert p.poll() is not None, f"{name} left running"


@pytest.mark.parametrize("two", [{"actors": 2, "api": True}], indirect=True)
def test_a_run_across_two_routers_is_exact(two):
    """Started from router-b's side, the run's control, transitions, acks, weights and
    bonus queries all cross the router link; the API on the other router sees every
    service; nothing is denied anywhere."""
    config = make_config({**SMALL, "episodes": 30})
    with session(two.secrets, "cli", two.b) as cli:
        two.wait_services(cli, 6)  # 5 services + the API
        watch = start_run(cli, config, actors=2)
        assert watch.wait(timeout=240) == "completed", watch.states
        wait_final_counts(watch, config)
        check_exact(watch, watch.assign["actors"], config)
        assert set(watch.assign["actors"]) == set(two.actors)
        workers = httpx.get(f"{two.url}/workers", timeout=10).json()["workers"]
        assert {w["id"] for w in workers} >= {"counter", "learner", "evaluator", *two.actors}
        two.no_denials(cli)


def test_a_router_restarted_while_the_other_carries_on(two):
    """router-b (actors, evaluator) is killed mid-run and started again on its port a
    second later: router `router` and its counter and learner carry on meanwhile (they
    still answer), router-b's clients reconnect by themselves, the peers that went away
    are back within their grace (MACB_PEER_GRACE_S), and the run completes exactly:
    transitions lost in the outage are resent, none is counted twice."""
    config = make_config({**SMALL, "episodes": 40})
    with session(two.secrets, "cli", two.a) as cli:
        two.wait_services(cli, 5)
        watch = start_run(cli, config, actors=2)
        wait_for(lambda: watch.rows, timeout=120, what="a first point")
        two.procs.kill("router-b", signal.SIGKILL)
        time.sleep(1.0)  # router `router` alone: its services still answer
        assert {i["id"] for i in discover(cli)} == {"counter", "learner"}
        assert watch.state() == "running", watch.states
        two.start_router("router-b", two.b, connect=two.a)
        assert watch.wait(timeout=240) == "completed", watch.states
        wait_final_counts(watch, config)
        check_exact(watch, watch.assign["actors"], config, faults=True)
        two.no_denials(cli)
