"""A run's start lost to one of its services, on real processes.

The scheduler puts a run's start once. A service that dies just after the run was
assigned to it never gets it and, restarted, rejoins only what its runs file (the
counter: its disk) holds: nothing of the run, or, for the counter, the run's ended
attempt whose stop never reached it (the counter was down then too). The run's other
services would wait on it for good. The API (and `macb start`'s watch) runs in this
process so that the test can kill the service in that window: its `send_start` is
wrapped to kill the service before the start goes out and start it again after. A
router, a counter, a learner, an evaluator and an actor are processes.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

import services.api.scheduler as scheduler
import shared.net.control as control
from shared.config import make_config
from shared.net.bus import Bus
from tests.harness import TINY, Cluster, start_api, wait_for, wait_services

EPISODES = 40


def answering(url: str, role: str) -> bool:
    workers = httpx.get(f"{url}/workers", timeout=10).json()["workers"]
    return any(w["role"] == role and w["answers"] for w in workers)


@contextlib.contextmanager
def api_on_a_cluster(tmp_path: Path, env: dict[str, str] | None = None) -> Iterator[tuple]:
    """A router, a counter, a learner, an evaluator and an actor as processes, the API in
    this process on them: (cluster, its URL), once every service answers it."""
    with Cluster(tmp_path, env=env) as cluster:
        router = cluster.router()
        cluster.services(actors=1)
        server = start_api(tmp_path, router)
        try:
            for role in ("counter", "learner", "evaluator", "actor"):
                wait_for(lambda r=role: answering(server.url, r), 120, what=f"the {role}")
            yield cluster, server.url
        finally:
            server.stop()


def ended(url: str, run: str, timeout: float) -> dict:
    """The run's record once it is neither queued nor running."""
    return wait_for(
        lambda: (
            (r := httpx.get(f"{url}/runs/{run}", timeout=10).json())["status"]
            not in ("queued", "running")
            and r
        ),
        timeout,
        what=f"run {run} to end",
    )


@pytest.mark.timeout(420)
def test_a_counter_that_missed_its_runs_start_is_sent_it_again(tmp_path, monkeypatch, caplog):
    caplog.set_level(logging.WARNING, logger="macb.api.scheduler")
    with api_on_a_cluster(tmp_path, {"MACB_PEER_GRACE_S": "8"}) as (cluster, url):
        exp = httpx.post(
            f"{url}/experiments", json={**TINY, "episodes": EPISODES}, timeout=30
        ).json()
        run = exp["runs"][0]["id"]

        def got() -> dict:
            return httpx.get(f"{url}/runs/{run}", timeout=10).json()

        wait_for(lambda: got()["points"] >= 1, 120, what="attempt 1's first point")
        # The counter dies holding attempt 1; the stop of that attempt never reaches it.
        cluster.kill("counter")
        httpx.post(f"{url}/experiments/{exp['id']}/stop", timeout=30)
        wait_for(lambda: got()["status"] == "stopped", 30, what="attempt 1 stopped")
        wait_for(
            lambda: all(
                w["run"] is None for w in httpx.get(f"{url}/workers", timeout=10).json()["workers"]
            ),
            60,
            what="the learner, evaluator and actor freed by the stop",
        )
        real = scheduler.send_start
        lost: list[int | None] = []

        def start_lost_to_the_counter(bus, run_id, config, assign, attempt=None):
            if lost:  # sent again: let it through
                return real(bus, run_id, config, assign, attempt)
            lost.append(attempt)
            cluster.kill("counter-2")  # dies just after the assignment
            real(bus, run_id, config, assign, attempt)
            cluster.service("counter", "counter", name="counter-3")

        monkeypatch.setattr(scheduler, "send_start", start_lost_to_the_counter)
        retried = httpx.post(f"{url}/experiments/{exp['id']}/retry", timeout=30).json()
        assert retried["retried"] == [run]
        # Back, it restores attempt 1 (unfinished on its disk); the queue takes it.
        cluster.service("counter", "counter", name="counter-2")
        done = ended(url, run, 300)
        assert lost == [2], "the retry's start was the one lost"
        assert done["status"] == "completed" and done["attempts"] == 2, done
        assert done["points"] == EPISODES // TINY["eval_every"]
        again = [r.message for r in caplog.records if "its start sent again" in r.message]
        assert again and "holds attempt 1 of the run, not 2" in again[0], again

        def counted() -> bool:
            live = got()["live"]
            return live.get("counter", {}).get("counted_transitions") == EPISODES * 20

        wait_for(counted, 30, what="attempt 2 counted in full, from nothing")
        log = cluster.log("counter-3")
        assert "attempt 2 started while serving attempt 1" in log, log[-3000:]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("role, sid", [("learner", "learner"), ("actor", "actor0")])
def test_a_learner_or_actor_that_missed_its_runs_start_is_sent_it_again(
    tmp_path, monkeypatch, caplog, role, sid
):
    """Killed as the run's start goes out and started again, it rejoins nothing (its
    runs file never had the run) while the run's other services wait on it."""
    caplog.set_level(logging.WARNING, logger="macb.api.scheduler")
    with api_on_a_cluster(tmp_path) as (cluster, url):
        real = scheduler.send_start
        sent: list[str] = []

        def start_lost_to_it(bus, run_id, config, assign, attempt=None):
            sent.append(run_id)
            if len(sent) == 1:
                cluster.kill(sid)  # dies just after the assignment
            real(bus, run_id, config, assign, attempt)
            if len(sent) == 1:
                cluster.service(role, sid, name=f"{sid}-2")

        monkeypatch.setattr(scheduler, "send_start", start_lost_to_it)
        exp = httpx.post(
            f"{url}/experiments", json={**TINY, "episodes": EPISODES}, timeout=30
        ).json()
        done = ended(url, exp["runs"][0]["id"], 240)
        assert done["status"] == "completed" and done["points"] == EPISODES // 4, done
        again = [r.message for r in caplog.records if "its start sent again" in r.message]
        assert again and f"{role} {sid} does not serve the run" in again[0], again
        assert len(sent) == 1 + len(again)


@pytest.mark.timeout(300)
def test_macb_starts_watch_sends_the_start_again_to_a_counter_that_missed_it(tmp_path, monkeypatch):
    """`macb start` (no API) watches its run by the API's rule, the lost start too: the
    counter, killed as the start goes out, comes back holding nothing of the run."""
    with Cluster(tmp_path) as cluster:
        router = cluster.router()
        cluster.services(actors=1)
        bus = Bus([router])
        try:
            wait_services(bus, 4)
            real = control.send_start
            sent: list[str] = []

            def start_lost_to_the_counter(bus, run_id, config, assign, attempt=None):
                sent.append(run_id)
                if len(sent) == 1:
                    cluster.kill("counter")  # dies just after the assignment
                real(bus, run_id, config, assign, attempt)
                if len(sent) == 1:
                    cluster.service("counter", "counter", name="counter-2")

            monkeypatch.setattr(control, "send_start", start_lost_to_the_counter)
            config = make_config({**TINY, "episodes": EPISODES})
            watch = control.start_run(bus, config)
            assert watch.wait(timeout=240) == "completed", watch.decision()
            assert len(sent) >= 2 and set(sent) == {watch.run}, sent
            assert len(watch.rows) == EPISODES // TINY["eval_every"]
        finally:
            bus.close()
