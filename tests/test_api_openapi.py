"""The API's HTTP contract as /openapi.json states it, over real HTTP (uvicorn on a
loopback port, no bus): a 405 names every method its path has, and the body schema
refuses what the API refuses (`seed` with a list of `seeds`)."""

from __future__ import annotations

import re

import httpx
import jsonschema_rs
import pytest

from services.api.main import ApiServer, Settings

METHODS = ("GET", "POST", "PUT", "PATCH", "DELETE")


@pytest.fixture(scope="module")
def url(tmp_path_factory):
    data = tmp_path_factory.mktemp("api-openapi")
    no_bus = ["tcp/127.0.0.1:1"]  # nothing listens there: runs stay queued
    with ApiServer(Settings(port=0, data_dir=data, connect=no_bus)) as server:
        yield server.url


def allow(response: httpx.Response) -> set[str]:
    return {m.strip() for m in response.headers["allow"].split(",")}


def test_a_405_allow_header_lists_every_method_its_path_has(url):
    """GET and POST /experiments are two routes; a PUT there named only POST."""
    r = httpx.put(f"{url}/experiments")
    assert r.status_code == 405 and allow(r) == {"GET", "POST"}
    assert r.json() == {"detail": "Method Not Allowed"}
    paths = httpx.get(f"{url}/openapi.json").json()["paths"]
    checked = 0
    for path, operations in paths.items():
        documented = {m.upper() for m in operations}
        concrete = re.sub(r"\{[^}]+\}", "x1", path)
        for method in set(METHODS) - documented:
            r = httpx.request(method, f"{url}{concrete}")
            assert r.status_code == 405, (method, path)
            assert allow(r) == documented, (method, path, r.headers["allow"])
            checked += 1
    assert checked >= 30


def test_the_schema_says_seed_and_seeds_exclude_each_other_as_the_api_does(url):
    spec = httpx.get(f"{url}/openapi.json").json()
    body = spec["paths"]["/experiments"]["post"]["requestBody"]["content"]["application/json"]
    schema = jsonschema_rs.Draft202012Validator(
        {**body["schema"], "components": spec["components"]}
    )
    tiny = {"task": "simple", "algo": "ddpg", "episodes": 4}
    for extra, valid in [
        ({"seed": 3, "seeds": [1, 2]}, False),
        ({"seed": 3, "seeds": [3]}, False),
        ({"seed": 3}, True),
        ({"seeds": [1, 2]}, True),
        ({"seed": 3, "seeds": None}, True),  # no list: the seed is the one
        ({}, True),
    ]:
        assert schema.is_valid({**tiny, **extra}) is valid, extra
        r = httpx.post(f"{url}/experiments", json={**tiny, **extra})
        assert r.status_code == (201 if valid else 422), (extra, r.text)
        if not valid:
            assert r.json()["detail"][0]["msg"] == (
                "seed: give either seed or seeds (a list), not both"
            )
    seeds = spec["components"]["schemas"]["ExperimentCreate"]["properties"]["seeds"]
    assert "Not with `seed`" in seeds["description"]
