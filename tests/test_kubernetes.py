"""deploy/kubernetes/ (docs/deploy.md, "On Kubernetes"): the kustomize base renders with
`kubectl kustomize`, every object it renders is valid against Kubernetes' OpenAPI schemas
(offline: the pinned `kubernetes-validate` ships them; `kubectl --dry-run=client` needs a
server), and its images, commands, ports, settings and mounts are docker-compose.yml's
(the one source of truth), the ids aside: those come from the node or the pod name.

No Kubernetes runs here, so nothing is applied to a cluster. Without kubectl the file
skips, saying so; `.ci/run` installs Debian's (`kubernetes-client`) when it is missing.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

from shared.net.roles import role_of

ROOT = Path(__file__).resolve().parent.parent
BASE = ROOT / "deploy" / "kubernetes"
KUBECTL = shutil.which("kubectl")
# Every Kubernetes minor the pinned kubernetes-validate ships schemas for, oldest and newest.
VERSIONS = ("1.25.0", "1.37.0")
SECRETS = "/run/secrets/macb"
# The ids compose gives its services, and what they become: a counter per node is named
# after its node, a slot's workers after their pod (slot-0, slot-1, ...).
IDS = {
    "counter": "counter-$(NODE_NAME)",
    "learner": "learner-$(SLOT)",
    "evaluator": "evaluator-$(SLOT)",
    "actor0": "actor-$(SLOT)",
}
# Where those variables come from (the downward API), as a pod would get them.
DOWNWARD = {"NODE_NAME": "spec.nodeName", "SLOT": "metadata.name"}
EXAMPLE = {"NODE_NAME": "node-a.example", "SLOT": "slot-3"}

pytestmark = pytest.mark.skipif(
    KUBECTL is None,
    reason="kubectl not found: `apt-get install kubernetes-client` (.ci/run does, as root)",
)


def kustomize(path: Path) -> list[dict[str, Any]]:
    """`kubectl kustomize PATH`, parsed: every object it renders."""
    assert KUBECTL is not None
    out = subprocess.run(
        [KUBECTL, "kustomize", str(path)], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    return [doc for doc in yaml.safe_load_all(out.stdout) if doc]


@pytest.fixture(scope="module")
def rendered() -> list[dict[str, Any]]:
    return kustomize(BASE)


def by_kind(objs: list[dict[str, Any]]) -> dict[tuple[str, str], dict[str, Any]]:
    return {(o["kind"], o["metadata"]["name"]): o for o in objs}


def containers(objs: list[dict[str, Any]]) -> dict[str, tuple[dict[str, Any], dict[str, Any]]]:
    """Every container of every workload, by name: (the container, its pod spec)."""
    found: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}
    for o in objs:
        if o["kind"] in ("Deployment", "DaemonSet", "StatefulSet"):
            pod = o["spec"]["template"]["spec"]
            for c in pod["containers"]:
                assert c["name"] not in found, f"two containers named {c['name']}"
                found[c["name"]] = (c, pod)
    return found


def expand(text: str, env: dict[str, str]) -> str:
    """Kubernetes' $(VAR) expansion in a command or an env value."""
    return re.sub(r"\$\(([A-Za-z_][A-Za-z0-9_]*)\)", lambda m: env.get(m[1], m[0]), text)


def compose() -> dict[str, dict[str, Any]]:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]


def test_the_base_renders_the_whole_cluster(rendered):
    assert set(by_kind(rendered)) == {
        ("Deployment", "router"),
        ("Service", "router"),
        ("DaemonSet", "counter"),
        ("StatefulSet", "slot"),
        ("Service", "slot"),
        ("Deployment", "api"),
        ("Service", "api"),
        ("PersistentVolumeClaim", "api-data"),
    }


@pytest.mark.parametrize("version", VERSIONS)
def test_every_object_is_valid_against_kubernetes_schemas(rendered, version):
    for obj in rendered:
        # strict: a misspelt or misplaced field is an error, not silently dropped
        kubernetes_validate.validate(obj, version, strict=True)


def test_the_validation_rejects_what_a_server_would(rendered):
    """The check above can fail: a misspelt field and a wrong type are refused."""
    slot = by_kind(rendered)[("StatefulSet", "slot")]
    typo = {**slot, "spec": {**slot["spec"], "podManagmentPolicy": "Parallel"}}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(typo, VERSIONS[-1], strict=True)
    wrong = {**slot, "spec": {**slot["spec"], "replicas": "one"}}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(wrong, VERSIONS[-1], strict=True)


def test_images_commands_and_settings_are_docker_compose_s(rendered):
    """Each compose service is one container here, with compose's image, command and
    environment; only the id (and so the bus user, which is the id) differs, taken from
    the downward API, and the API's token comes from a Secret, not the environment."""
    services, found = compose(), containers(rendered)
    name_of = {"actor0": "actor"}  # one actor per slot, named after its role
    assert set(found) == {name_of.get(s, s) for s in services}
    for name, svc in services.items():
        c, pod = found[name_of.get(name, name)]
        assert c["image"] == svc["image"], name
        env_list = c["env"]
        plain = {e["name"]: e["value"] for e in env_list if "value" in e}
        refs = {e["name"]: e["valueFrom"] for e in env_list if "valueFrom" in e}
        want_env = {k: v for k, v in svc["environment"].items() if k != "MACB_API_TOKEN"}
        want_cmd = list(svc["command"])
        if name in IDS:
            want_cmd[want_cmd.index("--id") + 1] = IDS[name]
            want_env["MACB_ZENOH_USER"] = IDS[name]
            (var,) = re.findall(r"\$\((\w+)\)", IDS[name])
            assert refs.pop(var) == {"fieldRef": {"fieldPath": DOWNWARD[var]}}, name
            # Kubernetes expands only variables defined earlier in the list
            names = [e["name"] for e in env_list]
            assert names.index(var) < names.index("MACB_ZENOH_USER"), name
            # the id names the service's role, as the bus's ACL reads it
            assert role_of(expand(IDS[name], EXAMPLE)) == svc["command"][2], name
        assert c["command"] == want_cmd, name
        assert "args" not in c, name
        assert plain == {k: str(v) for k, v in want_env.items()}, name
        if "MACB_API_TOKEN" in svc["environment"]:
            token = refs.pop("MACB_API_TOKEN")
            assert token == {"secretKeyRef": {"name": "macb-api", "key": "token"}}
        assert refs == {}, name
        # nothing else in the environment: no service links (*_SERVICE_HOST, *_PORT)
        assert pod.get("enableServiceLinks") is False, name


def test_ports_are_the_ones_compose_publishes(rendered):
    """The router and the API listen where compose publishes them, and their Services
    reach those ports; no other container listens."""
    override = yaml.safe_load((ROOT / "docker-compose.override.yml").read_text())["services"]
    published = {n: {int(p.rsplit(":", 1)[1]) for p in s["ports"]} for n, s in override.items()}
    objs, found = by_kind(rendered), containers(rendered)
    for name, (c, _) in found.items():
        ports = {p["containerPort"] for p in c.get("ports", [])}
        assert ports == published.get(name, set()), name
    for name, ports in published.items():
        c, _ = found[name]
        named = {p["name"]: p["containerPort"] for p in c["ports"]}
        svc = objs[("Service", name)]["spec"]
        assert {p["port"] for p in svc["ports"]} == ports
        assert {named.get(p["targetPort"], p["targetPort"]) for p in svc["ports"]} == ports
        labels = objs[("Deployment", name)]["spec"]["template"]["metadata"]["labels"]
        assert svc["selector"].items() <= labels.items(), name
        (listen,) = [a for a in c["command"] if a.startswith(("tls/0.0.0.0:", "0.0.0.0:"))]
        assert int(listen.rsplit(":", 1)[1]) in ports, name
    # services connect to the router's Service by the name its certificate carries
    assert compose()["learner"]["environment"]["MACB_ZENOH_CONNECT"] == "tls/router:7447"


def test_every_service_mounts_the_bus_secrets_and_its_data_as_in_compose(rendered):
    services, found = compose(), containers(rendered)
    for name, svc in services.items():
        c, pod = found["actor" if name == "actor0" else name]
        volumes = {v["name"]: v for v in pod["volumes"]}
        mounts = {m["mountPath"]: m for m in c["volumeMounts"]}
        assert f"./secrets:{SECRETS}:ro" in svc["volumes"]
        bus = mounts[SECRETS]
        assert bus.get("readOnly") is True, name
        assert volumes[bus["name"]]["secret"]["secretName"] == "macb-bus", name
        assert ("macb-data:/data" in svc["volumes"]) == ("/data" in mounts), name


def test_slots_are_workers_with_one_cpu_each_on_nodes_that_have_a_counter(rendered):
    objs = by_kind(rendered)
    slot, counter = objs[("StatefulSet", "slot")], objs[("DaemonSet", "counter")]
    pod = slot["spec"]["template"]["spec"]
    assert [c["name"] for c in pod["containers"]] == ["learner", "evaluator", "actor"]
    for c in pod["containers"]:
        assert c["resources"]["requests"]["cpu"] in ("1", 1), c["name"]
    # every node that runs slots runs a counter: a run's counter can be on its node
    assert pod["nodeSelector"] == counter["spec"]["template"]["spec"]["nodeSelector"]
    # each slot keeps its learner's cuts on its own volume, mounted where compose's is
    claims = [t["metadata"]["name"] for t in slot["spec"]["volumeClaimTemplates"]]
    assert claims == ["data"]
    assert slot["spec"]["serviceName"] == "slot" and ("Service", "slot") in objs
    assert objs[("Service", "slot")]["spec"]["clusterIP"] == "None"


def test_the_api_is_ready_when_it_answers_health(rendered):
    from services.api.main import TokenAuth

    (c, _), probe = containers(rendered)["api"], None
    probe = c["readinessProbe"]["httpGet"]
    named = {p["name"]: p["containerPort"] for p in c["ports"]}
    assert named.get(probe["port"], probe["port"]) == 8000
    # the probe carries no token: its path must be one the API serves without one
    assert probe["path"] in TokenAuth.OPEN


def test_the_secrets_it_needs_are_the_ones_the_docs_create(rendered):
    names: set[str] = set()

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            names.update(node[k]["name"] for k in ("secretKeyRef",) if k in node)
            names.update(node[k]["secretName"] for k in ("secret",) if k in node)
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(rendered)
    assert names == {"macb-bus", "macb-api"}
    docs = (ROOT / "docs" / "deploy.md").read_text()
    for name in names:
        assert f"kubectl create secret generic {name} " in docs, name


def kustomize_major() -> int:
    assert KUBECTL is not None
    out = subprocess.run([KUBECTL, "version", "--client"], capture_output=True, text=True)
    m = re.search(r"Kustomize Version: v(\d+)", out.stdout)
    return int(m[1]) if m else 2  # kubectl < 1.21 says no version: kustomize 2.0.3


def test_the_overlay_in_the_docs_sets_namespace_image_and_slots(tmp_path):
    """docs/deploy.md's overlay, rendered over the base: every object in its namespace,
    every container on its image, its number of slots."""
    if kustomize_major() < 4:
        pytest.skip("this kubectl's kustomize (2.0) reads no `replicas` or folder resources")
    docs = (ROOT / "docs" / "deploy.md").read_text()
    block = docs.split("<!-- kubernetes overlay: tests/test_kubernetes.py renders it -->")[1]
    overlay = yaml.safe_load(block.split("```yaml\n", 1)[1].split("```", 1)[0])
    overlay["resources"] = [os.path.relpath(BASE, tmp_path)]  # the docs' path, from here
    (tmp_path / "kustomization.yaml").write_text(yaml.safe_dump(overlay))
    objs = kustomize(tmp_path)
    (image,) = overlay["images"]
    want = f"{image['newName']}:{image['newTag']}"
    assert {o["metadata"].get("namespace") for o in objs} == {overlay["namespace"]}
    assert {c["image"] for c, _ in containers(objs).values()} == {want}
    (replicas,) = overlay["replicas"]
    assert by_kind(objs)[("StatefulSet", "slot")]["spec"]["replicas"] == replicas["count"] > 1
    for obj in objs:
        kubernetes_validate.validate(obj, VERSIONS[-1], strict=True)
