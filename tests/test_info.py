"""The info replies as typed values: each service's reply is the JSON map it was (same
keys in the same order), and a reader skips a reply that names no service."""

from __future__ import annotations

import json

from shared.net.info import ApiInfo, CounterInfo, ServiceInfo
from shared.net.messages import Resumed

RESUMED = Resumed("r", from_episode=4, updates=9, replay_rows=100, held_batches=0, seconds=0.2)


def test_a_services_info_is_the_map_it_was_and_reads_back():
    info = ServiceInfo("L", "learner", run="r", runs=["r"], rejects={"bad": 1}, rejects_total=1)
    info = ServiceInfo(**{**info.__dict__, "resumed": RESUMED.to_wire()})
    wire = json.loads(json.dumps(info.to_json()))
    keys = ["id", "role", "run", "runs", "rejects", "rejects_total", "restarts", "resumed"]
    keys.append("node")
    assert list(wire) == keys and wire["resumed"]["from_episode"] == 4
    assert ServiceInfo.from_json(wire) == info


def test_the_counters_info_lists_each_runs_stats_under_runs():
    stats = {"r": {"table_size": 3, "acked": {"a0": 10}}}
    info = CounterInfo("c0", "counter", runs=["r"], run_stats=stats, ready=True, snapshot_s=30.0)
    wire = json.loads(json.dumps(info.to_json()))
    assert (
        wire["runs"] == stats
        and list(wire)[3] == "runs"
        and list(wire)[-2:]
        == [
            "ready",
            "snapshot_s",
        ]
    )
    back = CounterInfo.from_json(wire)
    assert back is not None and back.run_stats == stats and back.ready and back.runs == ["r"]


def test_the_apis_info_names_its_http_and_no_resume():
    wire = ApiInfo("api", "api", http="http://127.0.0.1:8000").to_json()
    assert "resumed" not in wire and list(wire)[-1] == "http" and wire["runs"] == []


def test_a_reply_that_names_no_service_is_skipped():
    for bad in ([1], {"id": "x"}, {"id": 3, "role": "actor"}, "text"):
        assert ServiceInfo.from_json(bad) is None and CounterInfo.from_json(bad) is None
    odd = ServiceInfo.from_json({"id": "a0", "role": "actor", "rejects_total": "many"})
    assert odd is not None and odd.rejects_total == 0 and odd.run is None
