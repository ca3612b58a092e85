"""GET /workers (the live services, from their liveliness tokens and info answers) and
GET /health, with a real router and without any bus."""

from __future__ import annotations

import json

import httpx

from tests.harness import TINY, post, start_api, wait_for


def test_workers_lists_live_services_from_their_liveliness_tokens(client, router):
    from shared.net import bus as keys
    from shared.net.bus import Bus

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

        def listed() -> dict | None:
            # Until the fake learner's info answer is in too: /workers asks with a 1 s
            # timeout, which a loaded machine can miss once.
            got = {w["id"]: w for w in client.get("/workers").json()["workers"]}
            ok = len(got) >= 3 and got.get("fake-learner", {}).get("answers")
            return got if ok else None

        workers = wait_for(listed, timeout=10, what="workers")
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
