"""`macb up` and docker-compose.yml describe the same cluster."""

from pathlib import Path

import yaml

from shared.cluster import cluster_plan

ROOT = Path(__file__).resolve().parent.parent


def test_compose_runs_the_same_services_commands_and_settings_as_macb_up():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    plan = cluster_plan(1, "tcp/router:7447", "/data", listen="tcp/0.0.0.0:7447")
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


def test_compose_file_is_one_docker_compose_1_29_reads():
    """Debian's docker-compose is 1.29: no `version` key needed, but no compose-v2-only
    syntax either (an `env_file` entry as {path, required} needs v2.24)."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    for name, svc in compose["services"].items():
        for entry in svc.get("env_file", []):
            assert isinstance(entry, str), f"{name}: env_file {entry!r} needs compose v2.24"
        assert svc.get("restart", "on-failure") == "on-failure", name
        assert "macb-data:/data" in svc.get("volumes", ["macb-data:/data"]), name
    assert set(compose["volumes"]) == {"macb-data"}


def test_plan_gives_actors_distinct_ids_and_one_thread_each():
    plan = cluster_plan(3)
    ids = [s.args[s.args.index("--id") + 1] for s in plan if s.args[0] == "actor"]
    assert ids == ["actor0", "actor1", "actor2"]
    for s in plan:
        assert dict(s.env)["OMP_NUM_THREADS"] == "1"
