"""`macb up` and docker-compose.yml describe the same cluster."""

from pathlib import Path

import yaml

from cli.supervisor import cluster_plan

ROOT = Path(__file__).resolve().parent.parent


def test_compose_runs_the_same_services_commands_and_settings_as_macb_up():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    plan = cluster_plan(
        1, "tls/router:7447", "/data", listen="tls/0.0.0.0:7447", secrets="/run/secrets/macb"
    )
    assert set(compose) == {s.name for s in plan}
    images = {svc.get("image") for svc in compose.values()}
    assert images == {"macb:latest"}, "one image for every service"
    for spec in plan:
        svc = compose[spec.name]
        assert svc["command"] == ["macb", "serve", *spec.args], spec.name
        env = dict(svc["environment"])
        if spec.name == "api":  # the token comes from compose's environment, never the file
            assert "MACB_API_TOKEN" in env and env.pop("MACB_API_TOKEN") is None
        assert {k: str(v) for k, v in env.items()} == dict(spec.env), spec.name
        # the secure bus (the router listens off loopback): every service has the secrets
        assert "./secrets:/run/secrets/macb:ro" in svc["volumes"], spec.name


def test_a_secure_plan_signs_every_service_in_as_its_own_id():
    plan = cluster_plan(2, "tls/127.0.0.1:7447", secrets="/s")
    for spec in plan:
        env = dict(spec.env)
        assert env["MACB_ZENOH_SECRETS"] == "/s"
        sid = spec.args[spec.args.index("--id") + 1] if "--id" in spec.args else "router"
        assert env["MACB_ZENOH_USER"] == sid, spec
    assert all("MACB_ZENOH_USER" not in dict(s.env) for s in cluster_plan(2))


def load(name: str) -> dict:
    return yaml.safe_load((ROOT / name).read_text())["services"]


def test_default_override_publishes_the_router_and_api_on_loopback_only():
    ports = {name: svc.get("ports") for name, svc in load("docker-compose.override.yml").items()}
    assert ports == {"router": ["127.0.0.1:7447:7447"], "api": ["127.0.0.1:8000:8000"]}
    assert not any("ports" in svc for svc in load("docker-compose.yml").values())


def test_host_override_runs_macb_up_s_commands_on_loopback():
    """docker-compose.host.yml over docker-compose.yml is `macb up` with its defaults:
    every service on the host network, the router and the API on 127.0.0.1, and the
    plain bus (the secure settings emptied: loopback needs none, as `macb up`)."""
    base, host = load("docker-compose.yml"), load("docker-compose.host.yml")
    plan = cluster_plan(1, "tcp/127.0.0.1:7447", "/data", api="127.0.0.1:8000")
    assert set(host) == set(base) == {s.name for s in plan}
    for spec in plan:
        svc = {**base[spec.name], **host[spec.name]}
        env = {**base[spec.name]["environment"], **host[spec.name].get("environment", {})}
        env.pop("MACB_API_TOKEN", None)
        assert env.pop("MACB_ZENOH_SECRETS") == "" and env.pop("MACB_ZENOH_USER") == ""
        assert svc["network_mode"] == "host", spec.name
        assert svc["command"] == ["macb", "serve", *spec.args], spec.name
        assert {k: str(v) for k, v in env.items()} == dict(spec.env), spec.name


def test_compose_file_is_one_docker_compose_1_29_reads():
    """Debian's docker-compose is 1.29: no `version` key needed, but no compose-v2-only
    syntax either (an `env_file` entry as {path, required} needs v2.24)."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    for name, svc in compose["services"].items():
        for entry in svc.get("env_file", []):
            assert isinstance(entry, str), f"{name}: env_file {entry!r} needs compose v2.24"
        # Every service restarted when it dies, as `macb up`'s supervisor does.
        assert svc.get("restart") == "on-failure", name
        if name != "router":  # it keeps no data (only the secrets are mounted in it)
            assert "macb-data:/data" in svc["volumes"], name
    assert set(compose["volumes"]) == {"macb-data"}


def test_plan_gives_actors_distinct_ids_and_one_thread_each():
    plan = cluster_plan(3)
    ids = [s.args[s.args.index("--id") + 1] for s in plan if s.args[0] == "actor"]
    assert ids == ["actor0", "actor1", "actor2"]
    for s in plan:
        assert dict(s.env)["OMP_NUM_THREADS"] == "1"


def test_slots_give_each_run_its_own_learner_evaluator_and_actors():
    plan = cluster_plan(2, "tcp/127.0.0.1:7447", "/data", slots=3)
    names = [s.name for s in plan]
    assert names == [
        "router",
        "counter",
        "learner",
        "evaluator",
        "learner1",
        "evaluator1",
        "learner2",
        "evaluator2",
        *[f"actor{r}" for r in range(6)],
        "api",
    ]
    assert cluster_plan(1) == cluster_plan(1, slots=1)  # one slot: the plan compose mirrors
