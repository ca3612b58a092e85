"""deploy/kubernetes/ (docs/deploy.md, "On Kubernetes"): the kustomize base renders with
`kubectl kustomize`, every object it renders is valid against Kubernetes' OpenAPI schemas
(offline: the pinned `kubernetes-validate` ships them; `kubectl --dry-run=client` needs a
server), and its images, commands, ports, settings and mounts are docker-compose.yml's
(the one source of truth), the ids aside: those come from the node or the pod name.

No Kubernetes runs here, so nothing is applied to a cluster. Without kubectl the file
skips, saying so; `.ci/run` installs Debian's (`kubernetes-client`) when it is missing.
Opt-in (MACB_K8S_PODMAN=1, root): the rendered workloads played by podman as the Pods a
one-node cluster would run, and a run through the API completing exactly.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import kubernetes_validate
import pytest
import yaml

from shared.net.roles import role_of
from tests.conftest import free_port, offline, wait_for
from tests.harness import macb

ROOT = Path(__file__).resolve().parent.parent
BASE = ROOT / "deploy" / "kubernetes"
KUBECTL = shutil.which("kubectl")
PODMAN = shutil.which("podman")
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
        if c["command"][2] in ("counter", "learner", "evaluator", "actor"):
            # the node it runs on (a pod's host name is its own): the scheduler gives a
            # run the counter on its learner's node
            assert refs.pop("MACB_NODE") == {"fieldRef": {"fieldPath": "spec.nodeName"}}, name
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


def millicores(cpu: str | int) -> int:
    text = str(cpu)
    return int(text[:-1]) if text.endswith("m") else int(float(text) * 1000)


def test_slots_are_workers_with_one_cpu_each_on_nodes_that_have_a_counter(rendered):
    objs = by_kind(rendered)
    slot, counter = objs[("StatefulSet", "slot")], objs[("DaemonSet", "counter")]
    pod = slot["spec"]["template"]["spec"]
    assert [c["name"] for c in pod["containers"]] == ["learner", "evaluator", "actor"]
    # a slot (worker) asks one CPU, as `macb up --slots N` gives each slot a core: most of
    # it for the learner's update thread, a tenth each for the evaluator and the actor
    cpus = {c["name"]: millicores(c["resources"]["requests"]["cpu"]) for c in pod["containers"]}
    assert sum(cpus.values()) == 1000 and max(cpus, key=cpus.__getitem__) == "learner", cpus
    # every node that runs slots runs a counter: a run's counter can be on its node
    assert pod["nodeSelector"] == counter["spec"]["template"]["spec"]["nodeSelector"]
    # each slot keeps its learner's cuts on its own volume, mounted where compose's is
    claims = [t["metadata"]["name"] for t in slot["spec"]["volumeClaimTemplates"]]
    assert claims == ["data"]
    assert slot["spec"]["serviceName"] == "slot" and ("Service", "slot") in objs
    assert objs[("Service", "slot")]["spec"]["clusterIP"] == "None"


def test_the_api_is_ready_when_it_answers_health(rendered):
    from services.api.main import TokenAuth

    c, _ = containers(rendered)["api"]
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


def docs_overlay() -> dict[str, Any]:
    """docs/deploy.md's overlay (my-cluster/kustomization.yaml), parsed."""
    docs = (ROOT / "docs" / "deploy.md").read_text()
    block = docs.split("<!-- kubernetes overlay: tests/test_kubernetes.py renders it -->")[1]
    return yaml.safe_load(block.split("```yaml\n", 1)[1].split("```", 1)[0])


def docs_kubectl_commands() -> list[list[str]]:
    """Every kubectl command in docs/deploy.md's "On Kubernetes" shell blocks, as words
    (comments dropped; a command inside `$(...)` or after `&&` counts on its own)."""
    docs = (ROOT / "docs" / "deploy.md").read_text()
    section = docs.split("\n## On Kubernetes\n", 1)[1].split("\n## ", 1)[0]
    found: list[list[str]] = []
    for block in re.findall(r"```sh\n(.*?)```", section, re.S):
        for line in block.splitlines():
            code = re.sub(r"\s#.*", "", line)
            found += [m.split() for m in re.findall(r"\bkubectl\s[^;&|)]*", code)]
    return found


# kubectl commands on objects of no namespace (nodes, the namespace itself).
CLUSTER_SCOPED = (["label", "node"], ["get", "nodes"], ["create", "namespace"])


def namespace_flag(words: list[str]) -> str | None:
    """The namespace `-n NS`, `--namespace NS` or `--namespace=NS` names, else None."""
    for i, w in enumerate(words):
        if w in ("-n", "--namespace") and i + 1 < len(words):
            return words[i + 1]
        if w.startswith("--namespace="):
            return w.split("=", 1)[1]
    return None


def test_every_kubectl_command_in_the_docs_works_in_the_overlay_s_namespace():
    """The overlay puts every object in its namespace, so the Secrets its pods mount and
    the Service one port-forwards to are there: each namespaced command names it (else
    kubectl uses the current one, `default`, and the pods never find their Secrets), and
    the namespace is created before the first of them. `apply -k` of the overlay needs
    no flag: the overlay sets it (rendered below)."""
    namespace = docs_overlay()["namespace"]
    commands = docs_kubectl_commands()
    assert ["kubectl", "create", "secret", "generic", "macb-bus"] in [c[:5] for c in commands]
    create = ["kubectl", "create", "namespace", namespace]
    assert create in commands, f"the docs never run `{' '.join(create)}`"
    made = commands.index(create)
    for i, words in enumerate(commands):
        if words[1:3] in CLUSTER_SCOPED or words[1:3] == ["apply", "-k"]:
            continue
        assert namespace_flag(words) == namespace, " ".join(words)
        assert i > made, f"before `kubectl create namespace {namespace}`: {' '.join(words)}"


def test_the_overlay_in_the_docs_sets_namespace_image_and_slots(tmp_path):
    """docs/deploy.md's overlay, rendered over the base: every object in its namespace,
    every container on its image, its number of slots."""
    if kustomize_major() < 4:
        pytest.skip("this kubectl's kustomize (2.0) reads no `replicas` or folder resources")
    overlay = docs_overlay()
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


# ---------------------------------------------------------------- podman kube play
# Not Kubernetes, but real containers from the rendered manifests: the closest this
# machine gets. Podman 4.3 (Debian 12) plays Pods, Deployments and PVCs only, so each
# workload becomes the Pod(s) Kubernetes would make of it, with what a kubelet would do
# done here: the downward API and $(VAR) expanded (node "podman", pods slot-0...), the
# Secrets given as the folder `macb certs` wrote and the token. Commands, images' entry
# points, settings and mounts stay as rendered. Opt-in (it builds the image and runs a
# cluster): MACB_K8S_PODMAN=1, as root with podman.
PLAY = os.environ.get("MACB_K8S_PODMAN") == "1"
NODE = "podman"
# This VM's kernel lacks what podman's defaults need (crun refuses its hybrid cgroups;
# raising rlimits needs CAP_SYS_RESOURCE, which the sandbox withholds): runc and limits
# no higher than the shell's.
CONTAINERS_CONF = """[containers]
default_ulimits = ["nofile=20000:20000", "nproc=4096:4096"]
[engine]
runtime = "runc"
cgroup_manager = "cgroupfs"
"""
RUN = {
    "task": "simple",
    "algo": "ddpg",
    "explore": "dis-macb",
    "hidden": [64, 64],
    "batch_size": 32,
    "eval_every": 10,
    "seeds": [0],
}


def as_pods(
    objs: list[dict[str, Any]], image: str, secrets_dir: Path, token: str, prefix: str, host: Path
) -> list[dict[str, Any]]:
    """The workloads as the Pods (and PVCs) a cluster of one node named NODE would run."""
    out: list[dict[str, Any]] = []
    for o in objs:
        if o["kind"] == "PersistentVolumeClaim":
            out.append({**o, "metadata": {"name": f"{prefix}-{o['metadata']['name']}"}})
        if o["kind"] not in ("Deployment", "DaemonSet", "StatefulSet"):
            continue
        name, spec = o["metadata"]["name"], o["spec"]
        names = (
            [f"{name}-{i}" for i in range(spec["replicas"])]
            if o["kind"] == "StatefulSet"
            else [name]
        )
        for pod_name in names:
            pod = yaml.safe_load(yaml.safe_dump(spec["template"]["spec"]))  # a deep copy
            pod.pop("nodeSelector", None)
            pod["hostname"] = pod_name
            for t in spec.get("volumeClaimTemplates", []):
                claim = f"{prefix}-{t['metadata']['name']}-{pod_name}"
                out.append({"apiVersion": "v1", "kind": "PersistentVolumeClaim",
                            "metadata": {"name": claim}, "spec": t["spec"]})  # fmt: skip
                pod.setdefault("volumes", []).append(
                    {"name": t["metadata"]["name"], "persistentVolumeClaim": {"claimName": claim}}
                )
            for v in pod.get("volumes", []):
                if "secret" in v:
                    v.pop("secret")
                    v["hostPath"] = {"path": str(secrets_dir), "type": "Directory"}
                elif "hostPath" in v:  # the node's folder, here one of this test's
                    v["hostPath"]["path"] = str(host / v["name"])
                elif "persistentVolumeClaim" in v and not v["persistentVolumeClaim"][
                    "claimName"
                ].startswith(prefix):
                    v["persistentVolumeClaim"]["claimName"] = (
                        f"{prefix}-{v['persistentVolumeClaim']['claimName']}"
                    )
            for c in pod["containers"]:
                c["image"] = image
                c.pop("readinessProbe", None)  # polled by the test instead
                c.pop("resources", None)
                env: dict[str, str] = {}
                for e in c.get("env", []):
                    ref = e.pop("valueFrom", None)
                    if ref and "fieldRef" in ref:
                        path = ref["fieldRef"]["fieldPath"]
                        e["value"] = {"spec.nodeName": NODE, "metadata.name": pod_name}[path]
                    elif ref:
                        assert ref["secretKeyRef"] == {"name": "macb-api", "key": "token"}
                        e["value"] = token
                    e["value"] = expand(e["value"], env)
                    env[e["name"]] = e["value"]
                c["command"] = [expand(a, env) for a in c["command"]]
                if c["name"] == "api":
                    (port,) = c["ports"]
                    port["hostIP"], port["hostPort"] = "127.0.0.1", free_port()
            labels = spec["template"]["metadata"]["labels"]
            meta = {"name": pod_name, "labels": labels}
            out.append({"apiVersion": "v1", "kind": "Pod", "metadata": meta, "spec": pod})
    return out


@dataclass
class Played:
    """The manifests played by podman: its environment, the files played, the API."""

    env: dict[str, str]
    files: list[Path]
    pods: list[dict[str, Any]]
    url: str
    token: str

    def podman(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        assert PODMAN is not None
        return subprocess.run(
            [PODMAN, *args], capture_output=True, text=True, timeout=timeout, env=self.env
        )

    def client(self) -> httpx.Client:
        auth = {"authorization": f"Bearer {self.token}"}
        return httpx.Client(base_url=self.url, headers=auth, timeout=30)


def _ready(p: Played, ids: set[str]) -> bool:
    try:
        with p.client() as http:
            if not http.get("/health").json().get("bus"):
                return False
            workers = http.get("/workers").json()["workers"]
    except (httpx.HTTPError, ValueError, KeyError):
        return False
    return {w["id"] for w in workers if w["answers"]} >= ids


@pytest.fixture(scope="module")
def played(rendered, tmp_path_factory) -> Iterator[Played]:
    if not PLAY:
        pytest.skip("podman kube play is opt-in: MACB_K8S_PODMAN=1 (builds the image)")
    lacking = [t for t in ("podman", "runc", "debootstrap", "openssl") if not shutil.which(t)]
    if lacking or os.geteuid() != 0:
        pytest.skip(f"podman kube play here needs root, podman and runc; lacking: {lacking}")
    tmp = tmp_path_factory.mktemp("podman")
    conf = tmp / "containers.conf"
    conf.write_text(CONTAINERS_CONF)
    env = {**os.environ, "CONTAINERS_CONF": str(conf)}
    prefix = f"macbk8s{os.getpid()}"
    before = os.environ.get("CONTAINERS_CONF")
    os.environ["CONTAINERS_CONF"] = str(conf)  # for offline.ensure_image's podman build
    try:
        built = offline.ensure_image(PODMAN)  # as for docker, cached under its digest tag
    finally:
        os.environ.pop("CONTAINERS_CONF")
        if before is not None:
            os.environ["CONTAINERS_CONF"] = before
    secrets_dir = tmp / "secrets"
    users = ["learner-slot-0", "evaluator-slot-0", "actor-slot-0", f"counter-{NODE}"]
    macb("certs", str(secrets_dir), *[a for u in users for a in ("--user", u)], check=True)
    token = secrets.token_urlsafe(16)
    pods = as_pods(rendered, built.tag, secrets_dir, token, prefix, tmp / "node")
    (tmp / "node").mkdir()
    files = []
    first = {"PersistentVolumeClaim": 0, "router": 1}  # volumes, then the router
    pods.sort(key=lambda o: first.get(o["kind"], first.get(o["metadata"]["name"], 2)))
    for kind in ("PersistentVolumeClaim", "Pod"):
        for i, obj in enumerate(o for o in pods if o["kind"] == kind):
            f = tmp / f"{i:02d}-{kind}-{obj['metadata']['name']}.yaml"
            f.write_text(yaml.safe_dump(obj))
            files.append(f)
    api_port = next(
        c["ports"][0]["hostPort"]
        for p in pods if p["kind"] == "Pod"
        for c in p["spec"]["containers"] if c["name"] == "api"
    )  # fmt: skip
    p = Played(env, files, pods, f"http://127.0.0.1:{api_port}", token)
    net = p.podman("network", "create", prefix)
    assert net.returncode == 0, net.stderr
    try:
        t0 = time.monotonic()
        for f in files:  # the router first: the others connect to it by name
            out = p.podman("kube", "play", "--network", prefix, str(f))
            assert out.returncode == 0, f"{f.name}: {out.stdout}{out.stderr}"
        ids = {"counter-podman", "learner-slot-0", "evaluator-slot-0", "actor-slot-0"}
        wait_for(lambda: _ready(p, ids), timeout=300, interval=1, what="API and services")
        print(f"\npodman: {len(files)} objects played, cluster up in {time.monotonic() - t0:.0f} s")
        yield p
    finally:
        for obj in (o for o in pods if o["kind"] == "Pod"):
            logs = p.podman("pod", "logs", "--tail", "15", obj["metadata"]["name"])
            print(f"--- {obj['metadata']['name']}\n{(logs.stdout + logs.stderr)[-3000:]}")
        for f in reversed(files):
            p.podman("kube", "down", str(f), timeout=120)
        for obj in (o for o in pods if o["kind"] == "PersistentVolumeClaim"):
            p.podman("volume", "rm", "-f", obj["metadata"]["name"])
        p.podman("network", "rm", "-f", prefix)
        left = p.podman("pod", "ps", "-q", "--filter", f"network={prefix}").stdout.strip()
        assert left == "", f"pods left: {left}"


def test_podman_plays_the_manifests_and_a_run_completes_exactly(played):
    """The rendered commands, settings and mounts run as containers on the secure bus:
    every service signs in under its pod-derived id, a run posted over REST completes
    on slot-0's workers and the node's counter, every transition counted once."""
    episodes = 40
    with played.client() as http:
        exp = http.post("/experiments", json={**RUN, "episodes": episodes})
        assert exp.status_code == 201, exp.text
        run_id = exp.json()["runs"][0]["id"]
        run = wait_for(
            lambda: (
                (r := http.get(f"/runs/{run_id}").json())["status"] not in ("queued", "running")
                and r
            ),
            timeout=900,
            interval=1,
            what=f"run {run_id} to end",
        )
        points = http.get(f"/runs/{run_id}/metrics", params={"since": 0}).json()["points"]
    assert run["status"] == "completed", run
    assert run["assign"]["learner"] == "learner-slot-0"
    assert run["assign"]["counter"] == f"counter-{NODE}"
    assert [p["episode"] for p in points] == list(range(10, episodes + 1, 10))
    last = points[-1]
    assert last["counted_transitions"] == last["env_steps"] == episodes * 20
    assert last["replay_ratio"] == 1.0
