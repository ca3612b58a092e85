"""The API as a whole: its docs, schema and dashboard page, the token every call but
/health needs, and the addresses it refuses to listen on without one."""

from __future__ import annotations

import re

import httpx
import pytest

from services.api.main import Settings, check_bind
from shared.config import TrainConfig
from shared.metrics import CURVE_FIELDS
from tests.harness import TINY, free_port, macb, start_api


def test_health_docs_and_dashboard(client):
    assert client.get("/health").json() == {"status": "ok", "bus": True, "version": "0.1.0"}
    assert "swagger" in client.get("/docs").text.lower()
    spec = client.get("/openapi.json").json()
    for path in (
        "/experiments",
        "/experiments/{exp_id}",
        "/experiments/{exp_id}/stop",
        "/experiments/{exp_id}/curves",
        "/experiments/{exp_id}/metrics.csv",
        "/runs/{run_id}",
        "/runs/{run_id}/stop",
        "/runs/{run_id}/metrics",
        "/runs/{run_id}/metrics.csv",
        "/runs/{run_id}/events",
        "/workers",
        "/health",
    ):
        assert path in spec["paths"], path
    # The curves' metric names, listed for a client (each item's enum: shared.metrics).
    (metric,) = [
        q for q in spec["paths"]["/experiments/{exp_id}/curves"]["get"]["parameters"]
        if q["name"] == "metric"
    ]  # fmt: skip
    items = next(s["items"] for s in metric["schema"]["anyOf"] if s.get("type") == "array")
    assert items["enum"] == list(CURVE_FIELDS) and "success_rate" in items["enum"]
    body = spec["components"]["schemas"]["ExperimentCreate"]["properties"]
    assert {"seeds", "grid", "arms", "name", "beta", "k", "episodes", "task"} <= set(body)
    for schema in ("Grid", "Arm"):  # every config key but the seed, documented
        keys = set(spec["components"]["schemas"][schema]["properties"]) - {"name"}
        assert keys == set(TrainConfig.model_fields) - {"seed"}, schema
    page = client.get("/")
    assert page.status_code == 200 and "<svg" not in page.text.split("<script>")[0]
    external = re.findall(r"""(?:src|href)=["']?(?:https?:)?//|fetch\(["'`]https?:""", page.text)
    assert external == [], "no CDN: the page loads nothing from elsewhere"


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
            # the docs page a browser opens from the dashboard's link, and the schema it
            # loads with the token it was given
            docs = anon.get("/docs", params={"token": "s3cret"})
            assert docs.status_code == 200 and "/openapi.json?token=s3cret" in docs.text
            assert anon.get("/openapi.json", params={"token": "s3cret"}).json()["paths"]
            for page in ("/docs", "/openapi.json"):
                assert anon.get(page, params={"token": "nope"}).status_code == 401
                assert anon.post(page, params={"token": "s3cret"}).status_code == 401
    finally:
        server.stop()


def test_refuses_a_non_loopback_address_without_a_token(tmp_path):
    with pytest.raises(ValueError, match="MACB_API_TOKEN"):
        check_bind(Settings(host="0.0.0.0"))
    check_bind(Settings(host="0.0.0.0", token="t"))
    check_bind(Settings(host="127.0.0.1"))
    check_bind(Settings(host="::1"))
    for empty in ("", "  "):  # "Authorization: Bearer " must not be a password
        with pytest.raises(ValueError, match="empty"):
            check_bind(Settings(host="127.0.0.1", token=empty))
    listen = f"0.0.0.0:{free_port()}"
    no_token = {"MACB_API_TOKEN": None}
    proc = macb("serve", "api", "--listen-http", listen, "--data-dir", str(tmp_path), env=no_token)
    assert proc.returncode == 2
    assert "refusing to listen on 0.0.0.0" in proc.stdout + proc.stderr
    assert not (tmp_path / "api.sqlite3").exists(), "refused before touching the store"
