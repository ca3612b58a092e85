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
import time
from pathlib import Path

import httpx
import pytest

from tests.harness import (
    TINY,
    Cluster,
    assert_exact,
    wait_final_counts,
    wait_for,
    wait_services,
)

# TINY's run, long enough for a fault to land mid-run: 200 episodes, a point every 20.
CONFIG = {**TINY, "episodes": 200, "eval_every": 20, "learning_starts": 100}
# A lockstep group cannot run ahead of its learner (each step waits on its answer), so
# a fault at its second point (episode 40) lands mid-run however short it is; 120
# episodes leave 80 after it, at a lockstep group's pace.
GROUP_EPISODES = 120
# `macb up` as the matrix (and the soak) runs it; its learner cuts each second, so a
# resume starts from one.
UP = ("--actors", "2", "--group-size", "3", "--quiet-services")
UP_ENV = {"MACB_LEARNER_CUT_S": "1", "MACB_PEER_GRACE_S": "30"}
SERVICES = 6  # counter, learner, evaluator, actor0, actor1 and the API answer /workers


@pytest.fixture(scope="module")
def up(tmp_path_factory):
    """One `macb up` for the whole matrix."""
    tmp = tmp_path_factory.mktemp("faults")
    results: dict[str, dict] = {}
    with Cluster(tmp, env=UP_ENV) as cluster:
        cluster.results = results  # type: ignore[attr-defined]
        try:
            cluster.up(*UP, answering=SERVICES)
            yield cluster
        finally:
            (tmp / "fault-matrix.json").write_text(json.dumps(results, indent=2))
            print(json.dumps(results, indent=2))


def _post(up: Cluster, body: dict) -> list[str]:
    """An experiment posted over REST: its runs' ids."""
    r = httpx.post(f"{up.url}/experiments", json=body, timeout=10)
    assert r.status_code in (200, 201), r.text
    return [run["id"] for run in r.json()["runs"]]


def _fault(up: Cluster, fault: str, ids: list[str], hit, cut: bool) -> list[dict]:
    """Apply `hit` at the first run's second point (and, with `cut`, once the learner
    has written a cut of each run: a learner killed before its first cut resumes from
    its log alone); every run must then complete exactly. The time from the fault to
    the next point stored goes into the matrix's results."""
    wait_for(lambda: up.points(ids[0]) >= 2, timeout=180, what="the second point")
    if cut:
        for run_id in ids:
            checkpoint = up.data / "learner" / run_id / "checkpoint.pt"
            wait_for(checkpoint.exists, timeout=60, what="the learner's first cut")
    at_fault = up.points(ids[0])
    t0 = time.monotonic()
    hit()
    wait_for(lambda: up.points(ids[0]) > at_fault, timeout=180, what=f"a point after {fault}")
    recovery = time.monotonic() - t0
    wait_for(lambda: up.ended(*ids), timeout=300, what="the end")
    runs = [assert_exact(up.finished(run_id), faults="restarted").record for run_id in ids]
    reasons = [run["reason"] for run in runs]
    up.results[fault] = {  # type: ignore[attr-defined]
        "recovery_s": round(recovery, 2),
        "points_at_fault": at_fault,
        "restarts": up.restarts(),
        **({"reason": reasons[0]} if len(runs) == 1 else {"reasons": reasons}),
    }
    return runs


def _fault_run(up: Cluster, fault: str, seed: int, hit, cut: bool = False, **over) -> dict:
    """`_fault` on a run alone (`over`: config keys over CONFIG): the completed run."""
    ids = _post(up, {**CONFIG, "seed": seed, "name": f"fault-{seed}", **over})
    return _fault(up, fault, ids, hit, cut)[0]


def _group_fault(up: Cluster, fault: str, seeds: list[int], hit, cut: bool) -> list[dict]:
    """`_fault` on an experiment of len(seeds) lockstep runs, one group (`macb up
    --group-size 3`)."""
    body = {
        **CONFIG,
        "episodes": GROUP_EPISODES,
        "seeds": seeds,
        "interleave": "lockstep",
        "name": f"group-{seeds[0]}",
    }
    ids = _post(up, body)
    runs = _fault(up, fault, ids, hit, cut)
    for run in runs:
        assert run["assign"]["group"] == ids, run["assign"]
    return runs


KILLED = ["learner", "counter", "evaluator", "actor0", "router", "api"]


@pytest.mark.slow
@pytest.mark.parametrize("victim", KILLED)
def test_sigkill_mid_run_then_the_run_completes_exactly(up, victim):
    before = up.restarts()[victim]
    pid = up.pids()[victim]
    seed = 10 + KILLED.index(victim)
    hit = lambda: up.kill(victim)  # noqa: E731 (SIGKILL)
    run = _fault_run(up, f"SIGKILL {victim}", seed, hit, cut=victim == "learner")
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
def test_sigkill_of_the_learner_mid_lockstep_run_then_the_run_completes_exactly(up):
    """`interleave: lockstep` alone (one actor asking the learner for every action; a
    group of one, whose requests carry its own (obs,) rather than a group's (R, obs)):
    the actor's open act request is sent again until the restarted learner answers it
    from its cut and log, and the counts stay exact. The counter, actor and router
    killed under lockstep are the group test's below: the same code, R runs."""
    before = up.restarts()["learner"]
    hit = lambda: up.kill("learner")  # noqa: E731 (SIGKILL)
    run = _fault_run(
        up, "SIGKILL learner (lockstep)", 50, hit, cut=True,
        episodes=GROUP_EPISODES, interleave="lockstep",
    )  # fmt: skip
    assert run["assign"]["actors"] == ["actor0"]
    assert up.restarts()["learner"] == before + 1, "the supervisor restarted it once"
    learner = run["services"][run["assign"]["learner"]]
    assert learner["policy_lag"] == 0.0
    assert "resumed from the cut at episode" in (run["reason"] or ""), run["reason"]
    wait_for(up.ready, timeout=60, what="every service answering again")


GROUP_KILLED = ["learner", "counter", "evaluator", "actor0", "router"]


@pytest.mark.slow
@pytest.mark.parametrize("victim", GROUP_KILLED)
def test_sigkill_mid_group_then_every_run_of_it_completes_exactly(up, victim):
    """A group of 3 lockstep runs on one learner, actor and evaluator: a restarted
    learner resumes the whole group from its runs' cuts and logs, a restarted actor
    steps every world on from where the learner says, and every count stays exact."""
    before = up.restarts()[victim]
    seeds = [70 + 3 * GROUP_KILLED.index(victim) + j for j in range(3)]
    hit = lambda: up.kill(victim)  # noqa: E731 (SIGKILL)
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
        up.pause("learner", seconds=13)  # zenoh's lease is 10 s: its token goes, the others wait

    _fault_run(up, "SIGSTOP learner 13 s", 30, pause)
    assert up.pids()["learner"] == pid, "a paused learner is not restarted"


@pytest.mark.slow
def test_everything_killed_then_macb_up_again_resumes_the_run(up):
    """Last: SIGKILL of `macb up` and all its services, then `macb up` again on the same
    data dir: the run that was running resumes and completes exactly."""

    def everything():
        up.kill_all()
        up.up(*UP, answering=SERVICES)

    _fault_run(up, "SIGKILL all, macb up again", 40, everything)


# ------------------------------------------------------------------ supervisor
def test_a_service_that_keeps_dying_is_restarted_with_backoff_then_given_up(tmp_path):
    """`macb up`'s supervisor: restarts after 0.5, 1, 2, 4 s; the fifth death within a
    minute gives the service up (named), and cluster.json says how often it restarted."""
    from cli.supervisor import Cluster as Supervisor
    from cli.supervisor import ServiceSpec

    cluster = Supervisor([ServiceSpec("doomed", ("no-such-role",))], tmp_path / "logs", echo=False)
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
def _learner_rejoins(cluster, cut: dict) -> tuple[dict, Path]:
    """A learner restarted on a data dir whose cut is `cut`: its status for the run."""
    import torch

    from shared.config import make_config
    from shared.net.bus import Bus, k_status
    from shared.net.messages import Status
    from shared.net.wire import decode

    config = make_config({**CONFIG, "seed": 1}).model_dump(mode="json")
    run, data = "cut-check", cluster.data
    (data / "services").mkdir(parents=True)
    assign = {"learner": "learner", "counter": "counter", "evaluator": "ev", "actors": ["a0"]}
    (data / "services" / "learner.json").write_text(
        json.dumps({"run": run, "config": config, "assign": assign})
    )
    folder = data / "learner" / run
    folder.mkdir(parents=True)
    torch.save(cut, folder / "checkpoint.pt")
    before = (folder / "checkpoint.pt").read_bytes()
    statuses: list[Status] = []
    with Bus([cluster.endpoint]) as bus:
        bus.subscribe(k_status(run, "learner"), lambda k, p: statuses.append(decode(p, Status)))
        cluster.service("learner")
        wait_for(lambda: statuses, timeout=60, what="the learner's status")
    assert (folder / "checkpoint.pt").read_bytes() == before, "the cut was overwritten"
    assert sorted(p.name for p in folder.iterdir()) == ["checkpoint.pt", "transitions.wal"]
    return statuses[0], folder / "checkpoint.pt"


@pytest.mark.parametrize(
    "change, named",
    [
        ({"k": 32}, "k: 32 in the cut, 64 in the run"),
        ({"task": "spread"}, "task: 'spread' in the cut, 'speaker_listener' in the run"),
        ({"format": 3}, "cut format 3, this version reads 2"),
    ],
)
def test_a_cut_of_another_config_or_format_is_refused_naming_it(cluster, change, named):
    from shared.config import make_config

    fields = {k: v for k, v in change.items() if k != "format"}
    other = make_config({**CONFIG, "seed": 1, **fields}).model_dump(mode="json")
    cut = {"format": change.get("format", 1), "config": json.dumps(other), "counters": {}}
    status, path = _learner_rejoins(cluster, cut)
    assert status.state == "failed", status
    reason = status.reason
    assert named in reason and str(path) in reason, reason


@pytest.mark.slow
def test_a_learner_killed_with_its_newest_cut_torn_resumes_from_the_one_before(cluster):
    """Kill the learner, tear its newest cut in half, start it again by hand: it refuses
    that cut (naming it, renamed *.refused), resumes from the previous one plus its log,
    and the run completes exactly."""
    from shared.config import make_config
    from shared.net.bus import Bus
    from shared.net.control import start_run

    cluster.env["MACB_LEARNER_CUT_S"] = "0.5"
    cluster.services(1)
    config = make_config({**CONFIG, "seed": 2})
    with Bus([cluster.endpoint]) as bus:
        wait_services(bus, 4)
        watch = start_run(bus, config, actors=1)
        wait_for(
            lambda: watch.latest.get("learner", {}).get("cuts", 0) >= 3 and len(watch.rows) >= 2,
            timeout=120,
            what="cuts written and points stored",
        )
        cluster.kill("learner")
        folder = cluster.data / "learner" / watch.run
        newest = folder / "checkpoint.pt"
        newest.write_bytes(newest.read_bytes()[: newest.stat().st_size // 2])
        cluster.service("learner", name="learner2")
        assert watch.wait(timeout=240) == "completed", watch.states
        wait_final_counts(watch, config)
        assert_exact(watch, config)
    log = cluster.log("learner2")
    assert f"refusing cut {newest}" in log, log
    assert (folder / "checkpoint.pt.refused").exists()
    resumed = watch.states["learner"]["resumed"]
    assert resumed["from_episode"] > 0 and resumed["updates"] > 0, resumed


def test_a_logged_batch_reads_back_as_it_was_taken(tmp_path):
    """The learner's log (shared/persist/wal.py records, one byte column per field): a batch
    comes back bit for bit, and a torn last record is cut off on open."""
    import numpy as np

    from services.learner.intake import columns, log_columns
    from shared.net.messages import Transitions
    from shared.persist.wal import WriteAheadLog

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
    log.append("actor0", 40, n, log_columns(Transitions("r", "actor0", 40, **batch)))
    other = Transitions("r", "actor1", 0, **{**batch, "policy_version": 18})
    log.append("actor1", 0, n, log_columns(other))
    log.close()
    with open(tmp_path / "t.wal", "ab") as f:
        f.write(b"\x10\x00\x00\x00torn")  # a record cut short by a kill
    log, records = WriteAheadLog.open(tmp_path / "t.wal")
    log.close()
    assert [(r.actor, r.seq, r.n) for r in records] == [("actor0", 40, n), ("actor1", 0, n)]
    back = columns(records[0].keys, n)
    for name in ("obs", "act", "rew", "next_obs", "done", "collisions"):
        assert back[name].dtype == batch[name].dtype and np.array_equal(back[name], batch[name])
    assert back["policy_version"] == 17 and columns(records[1].keys, n)["policy_version"] == 18
