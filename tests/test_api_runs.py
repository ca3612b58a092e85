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


def test_macb_run_out_writes_every_point_of_a_run_longer_than_a_page(api, client, tmp_path):
    """`macb run --out` / `macb up --out` (write_results) read a run's points page by page:
    a figure 8 run has 40,000, the API's default page 10,000."""
    import json

    from cli.api import write_results
    from services.api.client import ApiClient

    exp = post(client, {**TINY, "seeds": [0]}).json()
    run = exp["runs"][0]["id"]
    n = 10_005
    assert Store(api.settings.db_path).add_points(run, [row(e) for e in range(1, n + 1)]) == n
    with ApiClient(api.url) as api_client:
        whole = client.get(f"/experiments/{exp['id']}").json()
        write_results(api_client, whole, tmp_path / "out", plot=False)
        paged = api_client.all_points(run, page=4_000)  # three pages, the last short
    assert [p["episode"] for p in paged] == list(range(1, n + 1))
    lines = (tmp_path / "out" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["episode"] for x in lines] == list(range(1, n + 1))
    assert len((tmp_path / "out" / "metrics.csv").read_text().splitlines()) == n + 1


def test_events_resume_after_last_event_id_and_refuse_one_that_is_not_a_seq(api, client):
    """Last-Event-ID (what a browser's EventSource sends on reconnecting) resumes after
    that seq; one that is not 1-19 ASCII digits is a 422, and one past SQLite's integers
    ends the stream as one past the last point does (it aborted it, an OverflowError)."""
    exp = post(client, {**TINY, "seeds": [0]}).json()
    run = exp["runs"][0]["id"]
    Store(api.settings.db_path).add_points(run, [row(e) for e in (4, 8, 12)])
    assert client.post(f"/runs/{run}/stop").json()["changed"] is True  # ended: streams end

    def events(last: bytes) -> list[str]:
        r = client.get(f"/runs/{run}/events", headers={"Last-Event-ID": last})
        assert r.status_code == 200, r.text
        return [x for x in r.text.splitlines() if x.startswith(("id:", "event:"))]

    after1 = events(b"1")
    assert [x for x in after1 if x.startswith("id:")] == ["id: 2", "id: 3"], after1
    assert after1[-1] == "event: end"
    beyond = events(b"9" * 19)  # > 2**62
    assert not [x for x in beyond if x.startswith("id:")] and beyond[-1] == "event: end"
    for bad in (b"\xb2", b"1" * 20, b"-1", b"1e3"):
        r = client.get(f"/runs/{run}/events", headers={"Last-Event-ID": bad})
        assert r.status_code == 422 and "last-event-id" in r.text.lower(), (bad, r.text)


def test_events_name_the_attempt_each_point_and_status_is_of(api, client):
    """A retry deletes a run's points and its new attempt's start again from the first
    episode, numbered on: a stream's client saw the episodes go back with nothing to
    say why. Every event names the attempt it is of."""
    import json

    exp = post(client, {**TINY, "seeds": [0]}).json()
    run = exp["runs"][0]["id"]
    store = Store(api.settings.db_path)
    store.add_points(run, [row(e) for e in (4, 8)])
    assert client.post(f"/runs/{run}/stop").json()["changed"] is True

    def events(since: int) -> list[tuple[str, dict]]:
        text = client.get(f"/runs/{run}/events", params={"since": since}).text
        blocks = [b for b in text.split("\n\n") if "event:" in b]
        out = []
        for b in blocks:
            lines = dict(x.split(": ", 1) for x in b.splitlines() if not x.startswith("id:"))
            out.append((lines["event"], json.loads(lines["data"])))
        return out

    first = events(0)
    assert [(e, d["attempt"]) for e, d in first] == [
        ("metric", 1),
        ("metric", 1),
        ("status", 1),
        ("end", 1),
    ]
    assert client.post(f"/experiments/{exp['id']}/retry").status_code == 200
    store.add_points(run, [row(4)], attempt=2)
    assert client.post(f"/runs/{run}/stop").json()["changed"] is True
    again = events(2)  # (a client that had the first attempt's two points)
    assert [(e, d["attempt"]) for e, d in again] == [("metric", 2), ("status", 2), ("end", 2)]
    assert again[0][1]["episode"] == 4 and again[0][1]["seq"] == 3
    store.close()
