"""The API over real HTTP (uvicorn on a loopback port, httpx) with a real SQLite file.

These tests need no training services: runs stay queued (no free services), metric
points are written into the store the way the scheduler writes them, and the
bus side is a real router. Whole runs on real services: tests/test_api_e2e.py.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import subprocess
import sys

import httpx
import pytest

from services.api.main import ApiServer, Settings, check_bind
from services.api.store import CSV_FIELDS, SCHEMA_VERSION, Store, StoreError
from tests.conftest import ROOT, free_port, wait_for

TINY = {
    "task": "speaker_listener",
    "algo": "cen-maddpg",
    "explore": "cen-macb",
    "k": 64,
    "episodes": 12,
    "eval_every": 4,
    "eval_episodes": 2,
    "hidden": [32, 32],
    "batch_size": 16,
}


def start_api(tmp_path, router: str | None, **settings) -> ApiServer:
    connect = [router] if router else ["tcp/127.0.0.1:1"]  # nothing listens on port 1
    return ApiServer(
        Settings(port=0, data_dir=tmp_path / "api", connect=connect, **settings)
    ).start()


@pytest.fixture
def api(router, tmp_path):
    server = start_api(tmp_path, router)
    yield server
    server.stop()


@pytest.fixture
def client(api):
    with httpx.Client(base_url=api.url, timeout=20) as c:
        yield c


def post(client, body, **kw):
    return client.post("/experiments", json=body, **kw)


def row(episode: int, **extra) -> dict:
    """A metric row with the evaluator's fields."""
    base = {f: float(episode) for f in CSV_FIELDS}
    base.update(episode=episode, env_steps=episode * 20, success_rate=episode / 100)
    return {**base, **extra}


# ---------------------------------------------------------------- resources
def test_experiment_expands_into_one_queued_run_per_seed_and_grid_point(client):
    r = post(client, {**TINY, "seeds": [0, 1], "grid": {"beta": [0.2, 0.8], "k": [64, 512]}})
    assert r.status_code == 201, r.text
    exp = r.json()
    assert exp["status"] == "queued" and exp["counts"] == {"queued": 8}
    assert exp["seeds"] == [0, 1] and exp["grid"] == {"beta": [0.2, 0.8], "k": [64, 512]}
    combos = {(r["config"]["beta"], r["config"]["k"], r["config"]["seed"]) for r in exp["runs"]}
    assert combos == {(b, k, s) for b in (0.2, 0.8) for k in (64, 512) for s in (0, 1)}
    for run in exp["runs"]:
        assert run["point"] == {"beta": run["config"]["beta"], "k": run["config"]["k"]}
        assert run["config"]["episodes"] == 12 and run["config"]["hidden"] == [32, 32]
        assert run["progress"] == {
            "episode": 0,
            "episodes": 12,
            "fraction": 0.0,
            "trained_episodes": 0,
        }
    # The run waits in the queue and says what for.
    run_id = exp["runs"][0]["id"]
    waiting = wait_for(
        lambda: client.get(f"/runs/{run_id}").json()["reason"], timeout=10, what="queue reason"
    )
    assert waiting.startswith("waiting: no free") and "learner" in waiting
    assert client.get(f"/runs/{run_id}").json()["status"] == "queued"
    listed = client.get("/experiments").json()
    assert listed["total"] == 1 and listed["experiments"][0]["id"] == exp["id"]
    assert client.get(f"/experiments/{exp['id']}").json()["runs"][3]["id"] == exp["runs"][3]["id"]


def test_seed_defaults_to_the_config_seed_and_name_is_kept(client):
    exp = post(client, {**TINY, "seed": 7, "name": "table 2, small"}).json()
    assert [r["seed"] for r in exp["runs"]] == [7]
    assert exp["name"] == "table 2, small" and exp["seeds"] == [7]
    assert "seed" not in exp["config"] and exp["config"]["k"] == 64


def test_stop_is_idempotent_and_says_when_it_does_nothing(client):
    exp = post(client, {**TINY, "seeds": [0, 1, 2]}).json()
    first = exp["runs"][0]["id"]
    r = client.post(f"/runs/{first}/stop").json()
    assert r["changed"] is True and r["run"]["status"] == "stopped"
    assert r["run"]["reason"] == "stopped by user"
    again = client.post(f"/runs/{first}/stop")
    assert again.status_code == 200
    assert again.json()["changed"] is False
    assert again.json()["detail"] == "run already stopped: nothing to stop"
    r = client.post(f"/experiments/{exp['id']}/stop").json()
    assert r["changed"] is True and r["stopped"] == [x["id"] for x in exp["runs"][1:]]
    assert r["experiment"]["status"] == "stopped"
    assert r["experiment"]["counts"] == {"stopped": 3}
    again = client.post(f"/experiments/{exp['id']}/stop").json()
    assert again["changed"] is False and again["stopped"] == []
    assert "nothing to stop" in again["detail"]


# ---------------------------------------------------------------- metrics
def test_metrics_json_csv_since_and_curves_serve_exactly_what_is_stored(api, client):
    exp = post(client, {**TINY, "seeds": [0, 1]}).json()
    a, b = (r["id"] for r in exp["runs"])
    store = Store(api.settings.db_path)  # a second connection, as the scheduler has
    rows_a = [row(e, success_rate=s) for e, s in ((4, 0.0), (8, 0.5), (12, 1.0))]
    rows_b = [row(e, success_rate=s, bonus_extra=1.5) for e, s in ((4, 0.5), (8, 0.5))]
    assert store.add_points(a, rows_a) == 3
    assert store.add_points(b, rows_b) == 2
    assert store.add_points(a, [row(8)]) == 0, "a repeated evaluation episode is not stored twice"

    page = client.get(f"/runs/{a}/metrics").json()
    assert page["status"] == "queued" and page["next_since"] == 3 and page["more"] is False
    assert [p["seq"] for p in page["points"]] == [1, 2, 3]
    assert [{k: v for k, v in p.items() if k != "seq"} for p in page["points"]] == rows_a
    newer = client.get(f"/runs/{a}/metrics", params={"since": 2}).json()
    assert [p["episode"] for p in newer["points"]] == [12] and newer["next_since"] == 3
    first = client.get(f"/runs/{a}/metrics", params={"limit": 2}).json()
    assert [p["seq"] for p in first["points"]] == [1, 2] and first["more"] is True
    assert client.get(f"/runs/{a}/metrics", params={"since": 3}).json()["points"] == []

    r = client.get(f"/runs/{b}/metrics.csv")
    assert r.headers["content-type"].startswith("text/csv")
    table = list(csv.DictReader(io.StringIO(r.text)))
    header = r.text.splitlines()[0].split(",")
    assert header == [*CSV_FIELDS, "bonus_extra"], "train's columns, services', then extras"
    assert [int(t["episode"]) for t in table] == [4, 8]
    assert [float(t["success_rate"]) for t in table] == [0.5, 0.5]

    curves = client.get(
        f"/experiments/{exp['id']}/curves", params={"metric": ["success_rate"]}
    ).json()
    (group,) = curves["metrics"]["success_rate"]
    assert group["runs"] == [a, b] and group["episode"] == [4, 8, 12]
    assert group["mean"] == pytest.approx([0.25, 0.5, 1.0])
    assert group["std"] == pytest.approx([0.25, 0.0, 0.0])
    assert group["lo"] == pytest.approx([0.0, 0.5, 1.0]) and group["n"] == [2, 2, 1]
    run = client.get(f"/runs/{a}").json()
    assert run["points"] == 3 and run["progress"]["episode"] == 12
    store.close()


def test_csv_columns_are_the_trainers_then_the_services():
    from shared.metrics import SERVICE_FIELDS
    from shared.trainer import METRIC_FIELDS

    assert CSV_FIELDS == METRIC_FIELDS + SERVICE_FIELDS


def test_everything_survives_a_restart_of_the_api(router, tmp_path):
    first = start_api(tmp_path, router)
    with httpx.Client(base_url=first.url) as c:
        exp = post(c, {**TINY, "seeds": [3, 4], "grid": {"k": [32, 64]}}).json()
        c.post(f"/runs/{exp['runs'][1]['id']}/stop")
        store = Store(first.settings.db_path)
        store.add_points(exp["runs"][0]["id"], [row(4), row(8)])
        store.close()
        before = c.get(f"/experiments/{exp['id']}").json()
        metrics = c.get(f"/runs/{exp['runs'][0]['id']}/metrics").json()
    first.stop()
    second = start_api(tmp_path, router)
    try:
        with httpx.Client(base_url=second.url) as c:
            after = c.get(f"/experiments/{exp['id']}").json()
            strip = lambda e: [{**r, "reason": None} for r in e["runs"]]  # noqa: E731
            assert strip(after) == strip(before)
            assert c.get(f"/runs/{exp['runs'][0]['id']}/metrics").json() == metrics
            assert after["runs"][1]["status"] == "stopped"
    finally:
        second.stop()


def test_a_newer_store_schema_is_refused(tmp_path):
    path = tmp_path / "s.sqlite3"
    Store(path).close()
    import sqlite3

    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION + 1,))
    with pytest.raises(StoreError, match="schema"):
        Store(path)


# ---------------------------------------------------------------- bad input
BAD_BODIES = [
    # (what, request kwargs, status, field named in the answer)
    ("malformed JSON", {"content": b'{"task": "spread",', "json_ct": True}, 400, "body"),
    ("not an object", {"json": [1, 2]}, 422, "body"),
    ("wrong type", {"json": {**TINY, "episodes": "many"}}, 422, "episodes"),
    ("wrong type in a list", {"json": {**TINY, "hidden": [32, "x"]}}, 422, "hidden.1"),
    ("bool for a list", {"json": {**TINY, "seeds": True}}, 422, "seeds"),
    ("out of range", {"json": {**TINY, "beta": 101}}, 422, "beta"),
    ("out of range k", {"json": {**TINY, "k": 0}}, 422, "k"),
    ("negative seed", {"json": {**TINY, "seeds": [-1]}}, 422, "seeds.0"),
    ("grid out of range", {"json": {**TINY, "grid": {"k": [64, 99999]}}}, 422, "grid.k.1"),
    ("NaN", {"content": b'{"beta": NaN}', "json_ct": True}, 422, "beta"),
    ("unknown field", {"json": {**TINY, "betta": 0.3}}, 422, "betta"),
    ("unknown grid key", {"json": {**TINY, "grid": {"gamma": [0.9]}}}, 422, "grid.gamma"),
    ("bad combination", {"json": {"task": "simple", "algo": "cen-maddpg"}}, 422, "config"),
    ("seed and seeds", {"json": {**TINY, "seed": 1, "seeds": [1]}}, 422, "seed"),
    ("repeated seed", {"json": {**TINY, "seeds": [1, 1]}}, 422, "seeds"),
    (
        "too many runs",
        {"json": {**TINY, "seeds": list(range(64)), "grid": {"k": [1, 2, 3, 4, 5]}}},
        422,
        "seeds x grid",
    ),
    ("huge body", {"json": {**TINY, "name": "x" * 70_000}}, 413, None),
    (
        "huge chunked body",
        {"content": iter([b"{" + b" " * 40_000] * 3), "json_ct": True},
        413,
        None,
    ),
    ("not JSON content type", {"content": json.dumps(TINY), "ct": "text/plain"}, 415, None),
    ("form body", {"data": {"task": "spread"}}, 415, None),
]


def test_bad_input_gets_the_right_status_names_the_field_and_changes_nothing(api, client):
    exp = post(client, {**TINY, "seeds": [0]}).json()
    run = exp["runs"][0]["id"]
    # The scheduler notes what the run waits for; from then on nothing should change.
    wait_for(lambda: client.get(f"/runs/{run}").json()["reason"], timeout=10, what="queued")
    store = Store(api.settings.db_path)
    before = store.snapshot()
    for what, kw, status, field in BAD_BODIES:
        kw = dict(kw)
        headers = {}
        if kw.pop("json_ct", False):
            headers["content-type"] = "application/json"
        if "ct" in kw:
            headers["content-type"] = kw.pop("ct")
        r = client.post("/experiments", headers=headers, **kw)
        assert r.status_code == status, (what, r.status_code, r.text)
        detail = r.json()["detail"]
        if field is not None:
            assert field in [e["field"] for e in detail], (what, detail)
            assert all(e["msg"] for e in detail)
    for method, path in [
        ("GET", "/experiments/nope"),
        ("POST", "/experiments/nope/stop"),
        ("GET", "/experiments/nope/curves"),
        ("GET", "/runs/nope"),
        ("POST", "/runs/nope/stop"),
        ("GET", "/runs/nope/metrics"),
        ("GET", "/runs/nope/metrics.csv"),
        ("GET", "/runs/nope/events"),
    ]:
        r = client.request(method, path)
        assert r.status_code == 404, (method, path, r.text)
        assert "nope" in r.json()["detail"]
    for path, params in [
        (f"/runs/{run}/metrics", {"since": -1}),
        (f"/runs/{run}/metrics", {"limit": 0}),
        (f"/runs/{run}/metrics", {"since": "x"}),
        ("/experiments", {"limit": 100_000}),
        (f"/experiments/{exp['id']}/curves", {"metric": "a b"}),
    ]:
        assert client.get(path, params=params).status_code == 422, (path, params)
    assert client.delete(f"/runs/{run}").status_code == 405
    assert store.snapshot() == before, "a refused request changed stored state"
    store.close()


# ---------------------------------------------------------------- cluster views
def test_workers_lists_live_services_from_their_liveliness_tokens(client, router):
    from shared import bus as keys
    from shared.bus import Bus

    fake = Bus([router])
    try:
        fake.token(keys.k_live("learner", "fake-learner"))
        fake.queryable(
            keys.k_info("learner", "fake-learner"),
            lambda k, p: json.dumps(
                {"id": "fake-learner", "role": "learner", "run": None, "rejects_total": 0}
            ).encode(),
        )
        fake.token(keys.k_live("actor", "mute-actor"))  # alive, answers no info
        workers = wait_for(
            lambda: (
                {w["id"]: w for w in client.get("/workers").json()["workers"]}
                if len(client.get("/workers").json()["workers"]) >= 3
                else None
            ),
            timeout=10,
            what="workers",
        )
    finally:
        fake.close()
    assert workers["fake-learner"]["role"] == "learner" and workers["fake-learner"]["answers"]
    assert workers["mute-actor"]["answers"] is False
    assert workers["api"]["role"] == "api"  # the API announces itself too
    gone = wait_for(
        lambda: "fake-learner" not in {w["id"] for w in client.get("/workers").json()["workers"]},
        timeout=10,
        what="token gone",
    )
    assert gone


def test_health_docs_and_dashboard(client):
    assert client.get("/health").json() == {"status": "ok", "bus": True, "version": "0.1.0"}
    assert "swagger" in client.get("/docs").text.lower()
    spec = client.get("/openapi.json").json()
    for path in (
        "/experiments",
        "/experiments/{exp_id}",
        "/experiments/{exp_id}/stop",
        "/runs/{run_id}",
        "/runs/{run_id}/stop",
        "/runs/{run_id}/metrics",
        "/runs/{run_id}/metrics.csv",
        "/runs/{run_id}/events",
        "/workers",
        "/health",
    ):
        assert path in spec["paths"], path
    body = spec["components"]["schemas"]["ExperimentCreate"]["properties"]
    assert {"seeds", "grid", "name", "beta", "k", "episodes", "task"} <= set(body)
    page = client.get("/")
    assert page.status_code == 200 and "<svg" not in page.text.split("<script>")[0]
    external = re.findall(r"""(?:src|href)=["']?(?:https?:)?//|fetch\(["'`]https?:""", page.text)
    assert external == [], "no CDN: the page loads nothing from elsewhere"


def test_without_a_bus_the_api_still_serves_its_store(tmp_path):
    server = start_api(tmp_path, None)
    try:
        with httpx.Client(base_url=server.url) as c:
            assert c.get("/health").json()["bus"] is False
            assert c.get("/workers").status_code == 503
            exp = post(c, TINY)
            assert exp.status_code == 201
            assert c.get(f"/runs/{exp.json()['runs'][0]['id']}").json()["status"] == "queued"
    finally:
        server.stop()


# ---------------------------------------------------------------- access
def test_a_token_is_required_on_every_call_but_health(tmp_path, router):
    server = start_api(tmp_path, router, token="s3cret")
    try:
        url = server.url
        with (
            httpx.Client(base_url=url) as anon,
            httpx.Client(base_url=url, headers={"Authorization": "Bearer s3cret"}) as ok,
            httpx.Client(base_url=url, headers={"Authorization": "Bearer wrong"}) as bad,
        ):
            assert anon.get("/health").status_code == 200
            for method, path in [
                ("GET", "/experiments"),
                ("POST", "/experiments"),
                ("GET", "/runs/x"),
                ("GET", "/workers"),
                ("GET", "/"),
                ("GET", "/docs"),
                ("GET", "/openapi.json"),
            ]:
                for c in (anon, bad):
                    r = c.request(method, path, json=TINY if method == "POST" else None)
                    assert r.status_code == 401, (method, path)
                    assert r.headers["www-authenticate"] == "Bearer"
            assert ok.get("/experiments").json()["total"] == 0, "refused posts stored nothing"
            assert ok.post("/experiments", json=TINY).status_code == 201
            assert ok.get("/workers").status_code == 200
            assert anon.get("/", params={"token": "s3cret"}).status_code == 200
            assert anon.get("/", params={"token": "nope"}).status_code == 401
    finally:
        server.stop()


def test_refuses_a_non_loopback_address_without_a_token(tmp_path):
    with pytest.raises(ValueError, match="MACB_API_TOKEN"):
        check_bind(Settings(host="0.0.0.0"))
    check_bind(Settings(host="0.0.0.0", token="t"))
    check_bind(Settings(host="127.0.0.1"))
    check_bind(Settings(host="::1"))
    env = {k: v for k, v in os.environ.items() if k != "MACB_API_TOKEN"}
    proc = subprocess.run(
        [sys.executable, "-m", "cli", "serve", "api", "--listen-http"]
        + [f"0.0.0.0:{free_port()}", "--data-dir", str(tmp_path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "refusing to listen on 0.0.0.0" in proc.stdout + proc.stderr
    assert not (tmp_path / "api.sqlite3").exists(), "refused before touching the store"
