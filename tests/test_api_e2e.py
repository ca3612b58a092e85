"""End to end: the API as a process (`macb serve api`) on a real local cluster.

A router, a counter, one learner, one evaluator and one actor run as processes on
loopback ports of their own; experiments go in over HTTP and every metric point is
checked against what the evaluator put on the bus, in the store, the JSON and the CSV.
One learner means one run at a time, so a second run waits in the queue.
"""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import threading
import time
from contextlib import closing

import httpx
import msgpack
import pytest

from services.api.client import parse_sse
from shared.net import bus as keys
from shared.net.bus import Bus
from shared.net.messages import Metrics, Status
from shared.net.wire import WireError, decode, encode
from tests.harness import TINY, api_cluster, macb, wait_for, write_config


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    with api_cluster(tmp_path_factory.mktemp("api-e2e")) as c:
        yield c


class BusRows:
    """Every evaluation row on macb/run/*/metrics/eval, as a plain subscriber sees it."""

    def __init__(self, endpoint: str) -> None:
        self.rows: dict[str, list[dict]] = {}
        self.lock = threading.Lock()
        self.bus = Bus([endpoint])
        self.bus.subscribe(keys.k_metrics("*", "eval"), self._on)

    def _on(self, key: str, payload: bytes) -> None:
        try:
            msg = decode(payload, Metrics)
        except WireError:
            return
        with self.lock:
            self.rows.setdefault(msg.run, []).append(msg.data)

    def wait(self, run: str, n: int) -> None:
        """Until `n` rows of `run` were heard (they come on this subscriber's own
        schedule, not the API's: a fixed sleep can be too short on a loaded machine)."""
        wait_for(lambda: len(self.rows.get(run, [])) >= n, timeout=30, what=f"{n} rows on the bus")

    def close(self) -> None:
        self.bus.close()


def follow(url: str, run_id: str, out: list, since: int = 0, timeout: float = 180) -> None:
    """Collect (event, data) from GET /runs/{id}/events until `end`."""
    with httpx.stream(
        "GET", f"{url}/runs/{run_id}/events", params={"since": since}, timeout=timeout
    ) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        for event, data in parse_sse(r.iter_lines()):
            out.append((event, data))
            if event == "end":
                return


def without_seq(point: dict) -> dict:
    return {k: v for k, v in point.items() if k != "seq"}


def check_csv_has(url: str, run_id: str, points: list[dict]) -> None:
    text = httpx.get(f"{url}/runs/{run_id}/metrics.csv").text
    table = list(csv.DictReader(io.StringIO(text)))
    assert len(table) == len(points)
    for line, p in zip(table, points, strict=True):
        for field in ("episode", "env_steps", "success_rate", "count1_pct", "counted_transitions"):
            assert float(line[field]) == pytest.approx(float(p[field])), (field, line, p)
        assert float(line["replay_ratio"]) == pytest.approx(p["replay_ratio"])


def test_two_seeds_queue_run_and_every_point_reaches_events_json_and_csv(cluster):
    url = cluster.url
    bus_rows = BusRows(cluster.endpoint)
    try:
        exp = httpx.post(f"{url}/experiments", json={**TINY, "seeds": [0, 1]}).json()
        run_ids = [r["id"] for r in exp["runs"]]
        events: dict[str, list] = {r: [] for r in run_ids}
        followers = [
            threading.Thread(target=follow, args=(url, r, events[r]), daemon=True) for r in run_ids
        ]
        for t in followers:
            t.start()
        # One learner: while the first run runs, the second waits in the queue.
        first = wait_for(
            lambda: (s := httpx.get(f"{url}/runs/{run_ids[0]}").json())["status"] != "queued" and s,
            timeout=30,
            what="first run started",
        )
        second = httpx.get(f"{url}/runs/{run_ids[1]}").json()
        if first["status"] == "running":
            assert second["status"] == "queued", second
        # Garbage on the run's keys is dropped by the API, which goes on.
        with Bus([cluster.endpoint]) as noise:
            for payload in (b"\x00garbage\xff", b"", msgpack.packb({"v": 99, "run": "x"})):
                noise.put(keys.k_metrics(run_ids[0], "eval"), payload)
                noise.put(keys.k_status(run_ids[0], "learner"), payload)
            other_run = encode(Metrics("other-run", source="eval", data={"episode": 4}))
            noise.put(keys.k_metrics(run_ids[0], "eval"), other_run)
        for t in followers:
            t.join(180)
            assert not t.is_alive(), "event stream did not end"
        final = httpx.get(f"{url}/experiments/{exp['id']}").json()
        assert final["status"] == "completed", final
        for run_id in run_ids:
            run = httpx.get(f"{url}/runs/{run_id}").json()
            assert run["status"] == "completed" and run["reason"] is None, run
            assert run["progress"]["fraction"] == 1.0 and run["points"] == 3
            assert run["assign"]["learner"] == "learner"
            assert run["assign"]["actors"] == ["actor0"]
            assert run["services"]["learner"]["state"] == "completed"

            def counted(run_id=run_id):
                live = httpx.get(f"{url}/runs/{run_id}").json()["live"]
                return live.get("counter", {}).get("counted_transitions") == 12 * 20

            # The counter's final stats follow the learner's end.
            wait_for(counted, timeout=10, what="the counter's final stats")
            streamed = [d for e, d in events[run_id] if e == "metric"]
            statuses = [d["status"] for e, d in events[run_id] if e == "status"]
            assert statuses[-1] == "completed" and "running" in statuses
            assert events[run_id][-1] == (
                "end",
                {"status": "completed", "reason": None, "seq": 3, "attempt": 1},
            )
            assert [p["episode"] for p in streamed] == [4, 8, 12]
            stored = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
            # the events carry exactly the stored points, each naming its attempt
            assert [{**p, "attempt": 1} for p in stored] == streamed
            # This test's subscriber hears the rows on its own, maybe after the API did.
            bus_rows.wait(run_id, len(stored))
            assert [without_seq(p) for p in stored] == bus_rows.rows[run_id], (
                "the store holds every row the evaluator published, as published"
            )
            check_csv_has(url, run_id, stored)
            for p in stored:
                assert p["env_steps"] == p["episode"] * 20
                assert 0.0 <= p["success_rate"] <= 1.0 and p["replay_ratio"] >= 0.0
        # The services are free again.
        workers = httpx.get(f"{url}/workers").json()["workers"]
        assert all(w["run"] is None for w in workers), workers
    finally:
        bus_rows.close()


def test_restarting_the_api_mid_run_loses_no_metric_and_the_run_goes_on(cluster):
    """The API is killed mid-run and stays down while the evaluator publishes: stored
    points are kept as they were, the points published meanwhile are filled in from the
    evaluator's history on restart, and the run completes with nothing missing."""
    url = cluster.url
    bus_rows = BusRows(cluster.endpoint)
    try:
        episodes = 600  # long enough to outlast the restart on a fast machine
        exp = httpx.post(f"{url}/experiments", json={**TINY, "episodes": episodes}).json()
        run_id = exp["runs"][0]["id"]
        wait_for(
            lambda: httpx.get(f"{url}/runs/{run_id}/metrics").json()["next_since"] >= 2,
            timeout=60,
            what="two points stored",
        )
        cluster.kill(cluster.api_name)  # SIGKILL: no goodbye, mid-write maybe
        at_kill = len(bus_rows.rows[run_id])
        wait_for(
            lambda: len(bus_rows.rows[run_id]) >= at_kill + 3,
            timeout=60,
            what="points published while the API is down",
        )
        while_down = len(bus_rows.rows[run_id]) - at_kill
        cluster.api("api-restarted")
        after_restart = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
        assert httpx.get(f"{url}/runs/{run_id}").json()["status"] == "running", (
            "the run should outlast the API's downtime; make it longer"
        )
        # Re-attached and filled: every row published so far is stored, in episode order.
        published_then = [r["episode"] for r in bus_rows.rows[run_id]]
        stored_then = [p["episode"] for p in after_restart]
        assert stored_then[: len(published_then)] == published_then[: len(stored_then)]
        assert len(stored_then) >= at_kill + while_down
        streamed: list = []
        follow(url, run_id, streamed)
        run = httpx.get(f"{url}/runs/{run_id}").json()
        assert run["status"] == "completed", run
        assert run["reason"] is None, run
        final = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
        assert final[: len(after_restart)] == after_restart, "stored points are kept as they were"
        assert [d for e, d in streamed if e == "metric"] == [{**p, "attempt": 1} for p in final]
        bus_rows.wait(run_id, episodes // 4)
        published = bus_rows.rows[run_id]
        assert len(published) == episodes // 4
        assert [p["episode"] for p in final] == [r["episode"] for r in published]
        for p, r in zip(final, published, strict=True):
            assert without_seq(p) == r
        print(f"{while_down} points published while the API was down, all filled in")
        check_csv_has(url, run_id, final)
    finally:
        bus_rows.close()


def test_a_run_whose_learner_dies_fails_with_the_reason_and_the_others_go_on(cluster):
    url = cluster.url
    long = httpx.post(f"{url}/experiments", json={**TINY, "episodes": 400}).json()
    short = httpx.post(f"{url}/experiments", json={**TINY, "seed": 5}).json()
    doomed, survivor = long["runs"][0]["id"], short["runs"][0]["id"]
    wait_for(
        lambda: httpx.get(f"{url}/runs/{doomed}").json()["points"] >= 1,
        timeout=60,
        what="the first run training",
    )
    assert httpx.get(f"{url}/runs/{survivor}").json()["status"] == "queued"
    cluster.kill("learner")  # SIGKILL
    run = wait_for(
        lambda: (r := httpx.get(f"{url}/runs/{doomed}").json())["status"] != "running" and r,
        timeout=30,
        what="the run to end",
    )
    assert run["status"] == "failed", run
    assert "learner" in run["reason"] and ("died" in run["reason"] or "gone" in run["reason"])
    assert run["points"] >= 1, "what it had stored is kept"
    # The queued run waits for a learner, and runs when one comes.
    waiting = wait_for(
        lambda: httpx.get(f"{url}/runs/{survivor}").json()["reason"], timeout=10, what="reason"
    )
    assert "learner" in waiting
    cluster.service("learner", name="learner2")
    done = wait_for(
        lambda: (
            (r := httpx.get(f"{url}/runs/{survivor}").json())["status"] not in ("queued", "running")
            and r
        ),
        timeout=120,
        what="the other run to end",
    )
    assert done["status"] == "completed", done
    assert done["points"] == 3
    stop = httpx.post(f"{url}/runs/{doomed}/stop").json()
    assert stop["changed"] is False and stop["detail"] == "run already failed: nothing to stop"
    assert httpx.get(f"{url}/experiments/{long['id']}").json()["status"] == "failed"


def test_a_stopped_run_retried_runs_afresh_under_its_id(cluster):
    """Stopped mid-run and queued again (POST /experiments/{id}/retry): the same run id
    runs from the start on the same services, its earlier points gone (the new ones
    numbered on after their last seq), and the counter counts the new attempt's
    transitions from nothing (not on top of the old ones)."""
    url = cluster.url
    episodes = 120
    exp = httpx.post(f"{url}/experiments", json={**TINY, "episodes": episodes}).json()
    run_id = exp["runs"][0]["id"]
    wait_for(
        lambda: httpx.get(f"{url}/runs/{run_id}").json()["points"] >= 2,
        timeout=60,
        what="two points stored",
    )
    httpx.post(f"{url}/experiments/{exp['id']}/stop")
    wait_for(
        lambda: all(w["run"] is None for w in httpx.get(f"{url}/workers").json()["workers"]),
        timeout=20,
        what="services freed by the stop",
    )
    stopped = httpx.get(f"{url}/runs/{run_id}").json()
    assert stopped["status"] == "stopped" and stopped["points"] >= 2
    last = httpx.get(f"{url}/runs/{run_id}/metrics").json()["next_since"]
    out = httpx.post(f"{url}/experiments/{exp['id']}/retry").json()
    assert out["retried"] == [run_id] and out["experiment"]["runs"][0]["attempts"] == 2
    run = wait_for(
        lambda: (
            (r := httpx.get(f"{url}/runs/{run_id}").json())["status"] not in ("queued", "running")
            and r
        ),
        timeout=180,
        what="the retried run to end",
    )
    assert run["status"] == "completed" and run["reason"] is None, run
    assert run["attempts"] == 2 and run["points"] == episodes // 4
    points = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
    first = points[0]["seq"]
    assert first > last and [p["seq"] for p in points] == list(range(first, first + len(points)))
    assert [p["episode"] for p in points] == list(range(4, episodes + 1, 4))

    def counted():
        live = httpx.get(f"{url}/runs/{run_id}").json()["live"]
        return live.get("counter", {}).get("counted_transitions") == episodes * 20

    wait_for(counted, timeout=10, what="the counter's final stats: counted afresh")
    again = httpx.post(f"{url}/experiments/{exp['id']}/retry").json()
    assert again["changed"] is False and again["retried"] == []


MARK = 0.123456  # a success rate no tiny run reaches: an ended attempt's row, if stored


def test_a_retry_on_another_learner_is_not_stopped_by_the_old_learners_late_answer(cluster):
    """The old attempt's learner, paused, answers its stop only after the retry started on
    a second learner, and the counter's answer comes late too: on the same run's status
    key, neither is the new attempt's (the run's monitor counts the services the run was
    assigned; a status names its attempt). Nor are the old attempt's evaluation rows,
    come late for points the new attempt has yet to reach: they were stored in its place
    (the store keeps the first row of an episode) before a row named its attempt."""
    url = cluster.url
    cluster.service("learner", "learner-b")
    wait_for(
        lambda: (
            sum(w["role"] == "learner" for w in httpx.get(f"{url}/workers").json()["workers"]) >= 2
        ),
        timeout=60,
        what="a second learner",
    )
    try:
        exp = httpx.post(f"{url}/experiments", json={**TINY, "episodes": 120}).json()
        run_id = exp["runs"][0]["id"]
        wait_for(
            lambda: httpx.get(f"{url}/runs/{run_id}").json()["points"] >= 1,
            timeout=60,
            what="a point stored",
        )
        old = httpx.get(f"{url}/runs/{run_id}").json()["assign"]["learner"]
        first = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"][0]
        point = {k: v for k, v in first.items() if k != "seq"} | {"success_rate": MARK}
        names = [n for n in ("learner-b", "learner2", "learner") if n in cluster.procs]
        name = (
            "learner-b"
            if old == "learner-b"
            else next(n for n in names if n != "learner-b" and cluster.procs[n].poll() is None)
        )
        os.kill(cluster.procs[name].pid, signal.SIGSTOP)
        paused = time.monotonic()
        try:
            httpx.post(f"{url}/experiments/{exp['id']}/stop")
            assert httpx.get(f"{url}/runs/{run_id}").json()["status"] == "stopped"
            httpx.post(f"{url}/experiments/{exp['id']}/retry")
            retried = wait_for(
                lambda: (r := httpx.get(f"{url}/runs/{run_id}").json())["status"] != "queued" and r,
                timeout=30,
                what="the retry to start",
            )
            assert retried["status"] == "running", retried  # (no late answer stopped it)
            assert retried["assign"]["learner"] != old
            # The old attempt's evaluator, late, for points of the new attempt's to come.
            stale = [
                Metrics(run_id, source="eval", attempt=1, data={**point, "episode": e})
                for e in (112, 116, 120)
            ]
            # The counter serves both attempts: its answer to the old one's stop may come
            # as late (a busy inbox); here the test sends what it would say.
            counter = retried["assign"]["counter"]
            late = Status(
                run_id, service=counter, state="stopped", detail={}, reason="late", attempt=1
            )
            now = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
            assert max((p["episode"] for p in now), default=0) < 112, "points to come"
            with closing(Bus([cluster.endpoint])) as bus:
                bus.put(keys.k_status(run_id, counter), encode(late))
                for msg in stale:
                    bus.put(keys.k_metrics(run_id, "eval"), encode(msg))
                time.sleep(1.0)  # (a put is sent on: the session must live till it is out)
        finally:
            os.kill(cluster.procs[name].pid, signal.SIGCONT)
        # Longer than Zenoh's lease (10 s) and the router could drop the paused learner's
        # session, and the stop with it: the late answer would not be the test's case.
        assert time.monotonic() - paused < 9, "the old learner was paused too long"
        run = wait_for(
            lambda: (
                (r := httpx.get(f"{url}/runs/{run_id}").json())["status"]
                not in ("queued", "running")
                and r
            ),
            timeout=180,
            what="the retried run to end",
        )
        assert run["status"] == "completed" and run["reason"] is None, run
        assert old not in run["services"], run["services"]
        assert run["attempts"] == 2 and run["points"] == 120 // 4
        stored = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
        assert [p["episode"] for p in stored] == list(range(4, 121, 4))
        assert all(p["success_rate"] != MARK for p in stored), "an ended attempt's rows"
    finally:
        cluster.kill("learner-b")


def test_cli_run_ls_plot_and_stop_through_the_api(cluster, tmp_path):
    url = cluster.url
    cfg = write_config(tmp_path / "tiny.yaml", TINY)
    out = tmp_path / "out"
    done = macb("run", str(cfg), "--seeds", "3", "4", "--api", url, "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    assert "completed" in done.stderr
    exp_id = done.stderr.split("experiment ", 1)[1].split(":", 1)[0]
    exp = httpx.get(f"{url}/experiments/{exp_id}").json()
    assert exp["status"] == "completed" and exp["seeds"] == [3, 4]
    for run in exp["runs"]:
        table = list(csv.DictReader((out / run["id"] / "metrics.csv").open()))
        assert [int(r["episode"]) for r in table] == [4, 8, 12]
        assert json.loads((out / run["id"] / "config.json").read_text()) == run["config"]
    assert (out / "plot.png").stat().st_size > 10_000
    # The experiment's CSV: every point of both runs, arm, seed and run first.
    table = list(csv.DictReader((out / "metrics.csv").open()))
    assert list(table[0])[:4] == ["arm", "seed", "run", "episode"]
    assert [(r["seed"], int(r["episode"])) for r in table] == [
        (s, e) for s in ("3", "4") for e in (4, 8, 12)
    ]
    assert {r["arm"] for r in table} == {"cen-maddpg + cen-macb"}

    listed = macb("ls", "--api", url)
    assert listed.returncode == 0 and exp_id in listed.stdout
    assert all(r["id"] in listed.stdout for r in exp["runs"])
    for run in exp["runs"]:
        (line,) = [x for x in listed.stdout.splitlines() if run["id"] in x]
        assert "arm=cen-maddpg + cen-macb " in line, line

    for source in (("--api", url), ("--db", str(cluster.data / "api.sqlite3"))):
        png = tmp_path / f"plot{source[0]}.png"
        plotted = macb("plot", exp_id, "-o", str(png), *source)
        assert plotted.returncode == 0, plotted.stderr
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000

    finished = macb("stop", exp["runs"][0]["id"], "--api", url)
    assert finished.returncode == 0 and "nothing to stop" in finished.stdout
    assert macb("stop", "no-such-id", "--api", url).returncode == 1

    bad = macb("run", str(cfg), "--beta", "1000", "--api", url)
    assert bad.returncode == 2 and "beta" in bad.stderr

    detached = macb("run", str(cfg), "--episodes", "400", "--detach", "--api", url)
    assert detached.returncode == 0, detached.stderr
    new_id = detached.stdout.strip().splitlines()[-1]
    stopped = macb("stop", new_id, "--api", url)
    assert stopped.returncode == 0 and "stopped 1 run(s)" in stopped.stdout
    final = httpx.get(f"{url}/experiments/{new_id}").json()
    assert final["status"] == "stopped" and final["runs"][0]["reason"] == "stopped by user"
    wait_for(
        lambda: all(w["run"] is None for w in httpx.get(f"{url}/workers").json()["workers"]),
        timeout=20,
        what="services freed by the stop",
    )
