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

import contextlib
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
            + ["--group-size", "3"]
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

    def end(self) -> None:
        """Stop `macb up`, then fail if any process the cluster ever had outlived it."""
        self.stop()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if (self.data / "cluster.json").exists():
            self.pids()
        for pid in self.seen:
            if _alive(pid):
                _kill(pid, signal.SIGKILL)
                pytest.fail(f"process {pid} outlived macb up")

    def kill_all(self) -> None:
        """SIGKILL `macb up` and every service: nothing is told, nothing flushes."""
        pids = self.pids()
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGKILL)
        self.proc.wait()
        for pid in pids.values():
            _kill(pid, signal.SIGKILL)


def _kill(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)


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
        cluster.end()
        (data / "fault-matrix.json").write_text(json.dumps(results, indent=2))
        print(json.dumps(results, indent=2))


def _get(up: Up, path: str) -> dict | None:
    try:
        r = httpx.get(f"{up.url}{path}", timeout=5)
        return r.json() if r.status_code == 200 else None
    except (httpx.HTTPError, ValueError):
        return None  # the API itself may be the one restarting


def _post_run(up: Up, seed: int, **over) -> str:
    body = {**CONFIG, "seed": seed, "name": f"fault-{seed}", **over}
    r = httpx.post(f"{up.url}/experiments", json=body, timeout=10)
    assert r.status_code in (200, 201), r.text
    return r.json()["runs"][0]["id"]


def _points(up: Up, run: str) -> int:
    row = _get(up, f"/runs/{run}")
    return row["points"] if row else -1


def _group_fault(up: Up, fault: str, seeds: list[int], hit, cut: bool) -> list[dict]:
    """`_fault_run` for a run group: an experiment of len(seeds) lockstep runs (one
    group: `macb up --group-size 3`), `hit` at its first run's second point; every run
    must complete exactly."""
    body = {**CONFIG, "seeds": seeds, "interleave": "lockstep", "name": f"group-{seeds[0]}"}
    r = httpx.post(f"{up.url}/experiments", json=body, timeout=10)
    assert r.status_code in (200, 201), r.text
    ids = [run["id"] for run in r.json()["runs"]]
    wait_for(lambda: _points(up, ids[0]) >= 2, timeout=180, what="the group's second point")
    if cut:
        for run_id in ids:
            checkpoint = up.data / "learner" / run_id / "checkpoint.pt"
            wait_for(checkpoint.exists, timeout=60, what="the learner's first cut")
    at_fault = _points(up, ids[0])
    t0 = time.monotonic()
    hit()
    wait_for(lambda: _points(up, ids[0]) > at_fault, timeout=180, what=f"a point after {fault}")
    recovery = time.monotonic() - t0

    def ended() -> bool:
        runs = [_get(up, f"/runs/{i}") or {} for i in ids]
        return all(run.get("status") not in (None, "queued", "running") for run in runs)

    wait_for(ended, timeout=300, what="the group's end")
    runs = [_check_exact(up, run_id) for run_id in ids]
    for run in runs:
        assert run["assign"]["group"] == ids, run["assign"]
    up.results[fault] = {  # type: ignore[attr-defined]
        "recovery_s": round(recovery, 2),
        "points_at_fault": at_fault,
        "restarts": up.restarts(),
        "reasons": [run["reason"] for run in runs],
    }
    return runs


def _check_exact(up: Up, run_id: str, episodes: int = EPISODES, every: int = EVAL_EVERY) -> dict:
    """The completed run's counts are exact and each of its points is stored once."""
    from shared.config import make_config

    run = _get(up, f"/runs/{run_id}")
    assert run is not None
    assert run["status"] == "completed", (run["status"], run["reason"], up.log())
    cfg = make_config(run["config"])
    assign, services = run["assign"], run["services"]
    learner, counter = services[assign["learner"]], services[assign["counter"]]
    collected = episodes * cfg.episode_len
    assert learner["ingested"] == collected, learner
    assert learner["updates"] == collected - cfg.learning_starts, learner
    assert learner["replay_ratio"] == 1.0, learner
    assert counter["counted_transitions"] == collected, counter
    page = _get(up, f"/runs/{run_id}/metrics?limit=100000")
    assert page is not None
    points = [p["episode"] for p in page["points"]]
    assert points == list(range(every, episodes + 1, every)), points
    return run


def _fault_run(up: Up, fault: str, seed: int, hit, cut: bool = False, **over) -> tuple[dict, float]:
    """Post a run (`over`: config keys over CONFIG), apply `hit` at its second point
    (and, with `cut`, once the learner has written a cut of it: a learner killed before
    its first cut resumes from its log alone); (the completed run, recovery s)."""
    run_id = _post_run(up, seed, **over)
    wait_for(lambda: _points(up, run_id) >= 2, timeout=120, what="the run's second point")
    if cut:
        checkpoint = up.data / "learner" / run_id / "checkpoint.pt"
        wait_for(checkpoint.exists, timeout=60, what="the learner's first cut")
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
    seed = 10 + KILLED.index(victim)
    hit = lambda: _kill(pid, 9)  # noqa: E731
    run, _ = _fault_run(up, f"SIGKILL {victim}", seed, hit, cut=victim == "learner")
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


LOCKSTEP_KILLED = ["learner", "counter", "actor0", "router"]


@pytest.mark.slow
@pytest.mark.parametrize("victim", LOCKSTEP_KILLED)
def test_sigkill_mid_lockstep_run_then_the_run_completes_exactly(up, victim):
    """`interleave: lockstep` (one actor asking the learner for every action): the
    actor's open act request is sent again until a learner answers it, a restarted
    learner answers from its cut and log, and the counts stay exact."""
    before = up.restarts()[victim]
    pid = up.pids()[victim]
    seed = 50 + LOCKSTEP_KILLED.index(victim)
    hit = lambda: _kill(pid, 9)  # noqa: E731
    cut = victim == "learner"
    run, _ = _fault_run(up, f"SIGKILL {victim} (lockstep)", seed, hit, cut, interleave="lockstep")
    assert run["assign"]["actors"] == ["actor0"]
    assert up.restarts()[victim] == before + 1, "the supervisor restarted it once"
    learner = run["services"][run["assign"]["learner"]]
    assert learner["policy_lag"] == 0.0
    wait_for(up.ready, timeout=60, what="every service answering again")


GROUP_KILLED = ["learner", "counter", "evaluator", "actor0", "router"]


@pytest.mark.slow
@pytest.mark.parametrize("victim", GROUP_KILLED)
def test_sigkill_mid_group_then_every_run_of_it_completes_exactly(up, victim):
    """A group of 3 lockstep runs on one learner, actor and evaluator: a restarted
    learner resumes the whole group from its runs' cuts and logs, a restarted actor
    steps every world on from where the learner says, and every count stays exact."""
    before = up.restarts()[victim]
    pid = up.pids()[victim]
    seeds = [70 + 3 * GROUP_KILLED.index(victim) + j for j in range(3)]
    hit = lambda: _kill(pid, 9)  # noqa: E731
    runs = _group_fault(up, f"SIGKILL {victim} (group of 3)", seeds, hit, victim == "learner")
    assert up.restarts()[victim] == before + 1, "the supervisor restarted it once"
    for run in runs:
        assert run["services"][run["assign"]["learner"]]["policy_lag"] == 0.0
        if victim == "learner":
            assert "resumed from the cut at episode" in (run["reason"] or ""), run["reason"]
    wait_for(up.ready, timeout=60, what="every service answering again")


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


# ------------------------------------------------------------------ supervisor
def test_a_service_that_keeps_dying_is_restarted_with_backoff_then_given_up(tmp_path):
    """`macb up`'s supervisor: restarts after 0.5, 1, 2, 4 s; the fifth death within a
    minute gives the service up (named), and cluster.json says how often it restarted."""
    from shared.cluster import Cluster, ServiceSpec

    cluster = Cluster([ServiceSpec("doomed", ("no-such-role",))], tmp_path / "logs", echo=False)
    t0 = time.monotonic()
    cluster.start()
    try:
        gone = wait_for(cluster.supervise, timeout=60, interval=0.05, what="the supervisor")
    finally:
        cluster.stop()
    took = time.monotonic() - t0
    assert gone == "doomed"
    assert cluster.restarts["doomed"] == 4
    assert took >= 0.5 + 1 + 2 + 4, f"backoff not respected: {took:.1f} s"
    state = json.loads((tmp_path / "cluster.json").read_text())
    assert state["doomed"]["restarts"] == 4 and state["doomed"]["alive"] is False
    assert "no-such-role" in (tmp_path / "logs" / "doomed.log").read_text()


# ------------------------------------------------------------------ the learner's cuts
def _learner_rejoins(procs, tmp_path, cut: dict) -> tuple[dict, Path]:
    """A learner restarted on a data dir whose cut is `cut`: its status for the run."""
    import torch

    from shared.bus import Bus, k_status
    from shared.config import make_config
    from shared.wire import decode

    config = make_config({**CONFIG, "seed": 1}).model_dump(mode="json")
    run, data = "cut-check", tmp_path / "data"
    (data / "services").mkdir(parents=True)
    assign = {"learner": "learner", "counter": "counter", "evaluator": "ev", "actors": ["a0"]}
    (data / "services" / "learner.json").write_text(
        json.dumps({"run": run, "config": config, "assign": assign})
    )
    folder = data / "learner" / run
    folder.mkdir(parents=True)
    torch.save(cut, folder / "checkpoint.pt")
    before = (folder / "checkpoint.pt").read_bytes()
    statuses: list[dict] = []
    with Bus([procs.endpoint]) as bus:
        bus.subscribe(k_status(run, "learner"), lambda k, p: statuses.append(decode(p, "status")))
        procs.start("learner", "learner", "--id", "learner", "--data-dir", str(data))
        wait_for(lambda: statuses, timeout=60, what="the learner's status")
    assert (folder / "checkpoint.pt").read_bytes() == before, "the cut was overwritten"
    assert sorted(p.name for p in folder.iterdir()) == ["checkpoint.pt", "transitions.wal"]
    return statuses[0], folder / "checkpoint.pt"


@pytest.mark.parametrize(
    "change, named",
    [
        ({"k": 32}, "k: 32 in the cut, 64 in the run"),
        ({"task": "spread"}, "task: 'spread' in the cut, 'speaker_listener' in the run"),
        ({"format": 2}, "cut format 2, this version reads 1"),
    ],
)
def test_a_cut_of_another_config_or_format_is_refused_naming_it(procs, tmp_path, change, named):
    from shared.config import make_config

    fields = {k: v for k, v in change.items() if k != "format"}
    other = make_config({**CONFIG, "seed": 1, **fields}).model_dump(mode="json")
    cut = {"format": change.get("format", 1), "config": json.dumps(other), "counters": {}}
    status, path = _learner_rejoins(procs, tmp_path, cut)
    assert status["state"] == "failed", status
    reason = status["detail"]["reason"]
    assert named in reason and str(path) in reason, reason


@pytest.mark.slow
def test_a_learner_killed_with_its_newest_cut_torn_resumes_from_the_one_before(procs, tmp_path):
    """Kill the learner, tear its newest cut in half, start it again by hand: it refuses
    that cut (naming it, renamed *.refused), resumes from the previous one plus its log,
    and the run completes exactly."""
    from shared.bus import Bus
    from shared.config import make_config
    from shared.control import start_run
    from tests.test_services_run import check_exact, start_cluster, wait_services

    procs.env["MACB_LEARNER_CUT_S"] = "0.5"
    data = start_cluster(procs, tmp_path, 1)
    config = make_config({**CONFIG, "seed": 2})
    with Bus([procs.endpoint]) as bus:
        wait_services(bus, 4)
        watch = start_run(bus, config, actors=1)
        wait_for(
            lambda: watch.latest.get("learner", {}).get("cuts", 0) >= 3 and len(watch.rows) >= 2,
            timeout=120,
            what="cuts written and points stored",
        )
        procs.kill("learner")
        folder = Path(data) / "learner" / watch.run
        newest = folder / "checkpoint.pt"
        newest.write_bytes(newest.read_bytes()[: newest.stat().st_size // 2])
        procs.start("learner2", "learner", "--id", "learner", "--data-dir", data)
        assert watch.wait(timeout=240) == "completed", watch.states
        wait_for(
            lambda: watch.latest["counter"]["counted_transitions"] == EPISODES * EPISODE_LEN,
            timeout=10,
            what="the counter's final stats",
        )
        check_exact(watch, watch.assign["actors"], config)
    log = procs.log("learner2")
    assert f"refusing cut {newest}" in log, log
    assert (folder / "checkpoint.pt.refused").exists()
    resumed = watch.states["learner"]["resumed"]
    assert resumed["from_episode"] > 0 and resumed["updates"] > 0, resumed


def test_a_logged_batch_reads_back_as_it_was_taken(tmp_path):
    """The learner's log (shared/wal.py records, one byte column per field): a batch
    comes back bit for bit, and a torn last record is cut off on open."""
    import numpy as np

    from services.learner.main import _columns, _log_columns
    from shared.wal import WriteAheadLog

    rng = np.random.default_rng(0)
    n = 20
    batch = {
        "obs": rng.normal(size=(n, 14)).astype(np.float32),
        "act": rng.uniform(size=(n, 5)).astype(np.float32),
        "rew": rng.normal(size=n).astype(np.float32),
        "next_obs": rng.normal(size=(n, 14)).astype(np.float32),
        "done": (rng.uniform(size=n) < 0.1).astype(np.float32),
        "collisions": rng.integers(0, 3, size=n).astype(np.int32),
        "policy_version": 17,
    }
    log, _ = WriteAheadLog.open(tmp_path / "t.wal")
    log.append("actor0", 40, n, _log_columns(batch))
    log.append("actor1", 0, n, _log_columns({**batch, "policy_version": 18}))
    log.close()
    with open(tmp_path / "t.wal", "ab") as f:
        f.write(b"\x10\x00\x00\x00torn")  # a record cut short by a kill
    log, records = WriteAheadLog.open(tmp_path / "t.wal")
    log.close()
    assert [(r.actor, r.seq, r.n) for r in records] == [("actor0", 40, n), ("actor1", 0, n)]
    back = _columns(records[0].keys, n)
    for name in ("obs", "act", "rew", "next_obs", "done", "collisions"):
        assert back[name].dtype == batch[name].dtype and np.array_equal(back[name], batch[name])
    assert back["policy_version"] == 17 and _columns(records[1].keys, n)["policy_version"] == 18
