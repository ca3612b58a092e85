"""The fault matrix (docs/reliability.md): each service killed mid-run under `macb up`.

One real supervised cluster (`macb up`: router, counter, learner, evaluator, two
actors, the API) on loopback ports of its own. For each fault a run is posted over
REST, the fault lands once the run has stored its second evaluation point, and the
run must complete exactly as if nothing had happened to its numbers: every collected
transition counted once and in replay (counted == collected == ingested), replay
ratio 1.000, every evaluation point stored once. The time from the fault to the next
point stored is what a user waits; it is written to `fault-matrix.json` in the test's
folder and printed (docs/reliability.md has a measured table).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from shared.cluster import free_port
from tests.conftest import ROOT, wait_for

EPISODES, EVAL_EVERY, EPISODE_LEN, LEARNING_STARTS = 200, 20, 20, 100
CONFIG = {
    "task": "speaker_listener",
    "algo": "cen-maddpg",
    "explore": "cen-macb",
    "k": 64,
    "episodes": EPISODES,
    "eval_every": EVAL_EVERY,
    "eval_episodes": 2,
    "hidden": [32, 32],
    "batch_size": 16,
    "learning_starts": LEARNING_STARTS,
}
SERVICES = 6  # counter, learner, evaluator, actor0, actor1 and the API answer /workers


class Up:
    """`macb up` as a user runs it, in its own session, ended by PID."""

    def __init__(self, data: Path) -> None:
        self.data = data
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None
        self.seen: set[int] = set()  # every PID the cluster ever had

    def start(self) -> None:
        env = {
            **os.environ,
            "MACB_LEARNER_CUT_S": "1",  # cuts often, so a resume starts from one
            "MACB_PEER_GRACE_S": "30",
        }
        log = open(self.data / "up.log", "ab")  # noqa: SIM115 (the child owns it)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "cli", "up", "--actors", "2", "--endpoint", self.endpoint]
            + ["--api-port", str(self.port), "--data-dir", str(self.data), "--quiet-services"],
            cwd=ROOT,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        wait_for(self.ready, timeout=120, interval=0.3, what="macb up: API and services")

    def ready(self) -> bool:
        assert self.proc is not None
        assert self.proc.poll() is None, self.log()
        try:
            workers = httpx.get(f"{self.url}/workers", timeout=5).json()["workers"]
        except (httpx.HTTPError, ValueError, KeyError):
            return False
        return len([w for w in workers if w["answers"]]) >= SERVICES

    def pids(self) -> dict[str, int]:
        state = json.loads((self.data / "cluster.json").read_text())
        pids = {name: s["pid"] for name, s in state.items()}
        self.seen.update(pids.values())
        return pids

    def restarts(self) -> dict[str, int]:
        state = json.loads((self.data / "cluster.json").read_text())
        return {name: s["restarts"] for name, s in state.items()}

    def log(self) -> str:
        return (self.data / "up.log").read_text(errors="replace")[-4000:]

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=60)

    def kill_all(self) -> None:
        """SIGKILL `macb up` and every service: nothing is told, nothing flushes."""
        pids = self.pids()
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait()
        for pid in pids.values():
            _kill(pid, signal.SIGKILL)


def _kill(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie of ours is not running
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


@pytest.fixture(scope="module")
def up(tmp_path_factory):
    data = tmp_path_factory.mktemp("faults")
    cluster = Up(data)
    results: dict[str, dict] = {}
    cluster.results = results  # type: ignore[attr-defined]
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()
        if cluster.proc is not None and cluster.proc.poll() is None:
            cluster.proc.kill()
        if (data / "cluster.json").exists():
            cluster.pids()
        for pid in cluster.seen:
            if _alive(pid):
                _kill(pid, signal.SIGKILL)
                pytest.fail(f"process {pid} outlived macb up")
        (data / "fault-matrix.json").write_text(json.dumps(results, indent=2))
        print(json.dumps(results, indent=2))


def _get(up: Up, path: str) -> dict | None:
    try:
        r = httpx.get(f"{up.url}{path}", timeout=5)
        return r.json() if r.status_code == 200 else None
    except (httpx.HTTPError, ValueError):
        return None  # the API itself may be the one restarting


def _post_run(up: Up, seed: int) -> str:
    body = {**CONFIG, "seed": seed, "name": f"fault-{seed}"}
    r = httpx.post(f"{up.url}/experiments", json=body, timeout=10)
    assert r.status_code in (200, 201), r.text
    return r.json()["runs"][0]["id"]


def _points(up: Up, run: str) -> int:
    row = _get(up, f"/runs/{run}")
    return row["points"] if row else -1


def _check_exact(up: Up, run_id: str) -> dict:
    run = _get(up, f"/runs/{run_id}")
    assert run is not None
    assert run["status"] == "completed", (run["status"], run["reason"], up.log())
    assign, services = run["assign"], run["services"]
    learner, counter = services[assign["learner"]], services[assign["counter"]]
    collected = EPISODES * EPISODE_LEN
    assert learner["ingested"] == collected, learner
    assert learner["updates"] == collected - LEARNING_STARTS, learner
    assert learner["replay_ratio"] == 1.0, learner
    assert counter["counted_transitions"] == collected, counter
    page = _get(up, f"/runs/{run_id}/metrics?limit=1000")
    assert page is not None
    episodes = [p["episode"] for p in page["points"]]
    assert episodes == list(range(EVAL_EVERY, EPISODES + 1, EVAL_EVERY)), episodes
    return run


def _fault_run(up: Up, fault: str, seed: int, hit) -> tuple[dict, float]:
    """Post a run, apply `hit` at its second point; (the completed run, recovery s)."""
    run_id = _post_run(up, seed)
    wait_for(lambda: _points(up, run_id) >= 2, timeout=120, what="the run's second point")
    at_fault = _points(up, run_id)
    t0 = time.monotonic()
    hit()
    wait_for(lambda: _points(up, run_id) > at_fault, timeout=180, what=f"a point after {fault}")
    recovery = time.monotonic() - t0
    wait_for(
        lambda: (
            (_get(up, f"/runs/{run_id}") or {}).get("status") not in (None, "queued", "running")
        ),
        timeout=240,
        what="the run's end",
    )
    run = _check_exact(up, run_id)
    up.results[fault] = {  # type: ignore[attr-defined]
        "recovery_s": round(recovery, 2),
        "points_at_fault": at_fault,
        "restarts": up.restarts(),
        "reason": run["reason"],
    }
    return run, recovery


KILLED = ["learner", "counter", "evaluator", "actor0", "router", "api"]


@pytest.mark.slow
@pytest.mark.parametrize("victim", KILLED)
def test_sigkill_mid_run_then_the_run_completes_exactly(up, victim):
    before = up.restarts()[victim]
    pid = up.pids()[victim]
    run, _ = _fault_run(up, f"SIGKILL {victim}", 10 + KILLED.index(victim), lambda: _kill(pid, 9))
    assert up.restarts()[victim] == before + 1, "the supervisor restarted it once"
    assert up.pids()[victim] != pid
    if victim == "learner":
        assert "resumed from the cut at episode" in (run["reason"] or ""), run["reason"]
        resumed = run["services"][run["assign"]["learner"]]["resumed"]
        assert resumed["from_episode"] is not None and resumed["from_episode"] > 0, resumed
    wait_for(up.ready, timeout=60, what="every service answering again")
    workers = httpx.get(f"{up.url}/workers", timeout=5).json()["workers"]
    if victim != "router":  # the router announces no token; the others say how often
        (mine,) = [w for w in workers if w["id"] == victim]
        assert mine["restarts"] == before + 1, mine


@pytest.mark.slow
def test_sigstop_of_the_learner_past_its_lease_then_sigcont(up):
    pid = up.pids()["learner"]

    def pause():
        os.kill(pid, signal.SIGSTOP)
        time.sleep(13)  # zenoh's lease is 10 s: its token goes, the others wait
        os.kill(pid, signal.SIGCONT)

    _fault_run(up, "SIGSTOP learner 13 s", 30, pause)
    assert up.pids()["learner"] == pid, "a paused learner is not restarted"


@pytest.mark.slow
def test_everything_killed_then_macb_up_again_resumes_the_run(up):
    """Last: SIGKILL of `macb up` and all its services, then `macb up` again on the same
    data dir: the run that was running resumes and completes exactly."""

    def everything():
        up.kill_all()
        up.start()

    _fault_run(up, "SIGKILL all, macb up again", 40, everything)
