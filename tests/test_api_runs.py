"""A run's resources: GET /runs/{id}, its stop, its metrics as JSON (paged by `since`)
and as CSV, over real HTTP with a real SQLite file; points are written into the store
as the scheduler writes them. Its events stream: tests/test_api_e2e.py."""

from __future__ import annotations

import csv
import io

import pytest

from services.api.store import CSV_FIELDS, Store
from tests.harness import TINY, post, row


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
