"""The soak (docs/reliability.md, "Soak"): a run group at thesis settings under random
faults for --minutes, every count exact at the end. Long: run it with `make soak`
(pytest -m soak -s; MACB_SOAK_MINUTES, default 20); neither `make test` nor
`make test-slow` runs it.

One real `macb up --group-size 3` (tests/test_faults.py's) runs an experiment of
three lockstep runs (figure 8's sparse Cen-MACB arm: speaker_listener, Cen-MADDPG +
Cen-MACB k 512, beta 0.8, 400-300 networks, batch 100; seeds 0-2; `profile: thesis`).
Every 10-60 s (uniform) one fault lands: SIGKILL of a service (the supervisor restarts
it) or SIGSTOP for 1-15 s then SIGCONT, the service drawn from the learner, counter,
evaluator, actor, router and API; twice two services at once. Faults stop after the
soak's minutes; then every run must complete with counted == collected == ingested,
updates == collected - warm-up, replay ratio 1.0 and every point stored once. What
happened (each fault, the time to the next stored point after it, the counts) is
printed and written to soak.json in the test's folder.
"""

from __future__ import annotations

import json
import os
import random
import time

import httpx
import pytest

from tests.harness import ROOT, Cluster, assert_exact, wait_for
from tests.test_faults import SERVICES, UP, UP_ENV

MINUTES = float(os.environ.get("MACB_SOAK_MINUTES", "20"))
EVAL_EVERY = 50
VICTIMS = ["learner", "counter", "evaluator", "actor0", "router", "api"]


def soak_body(episodes: int) -> dict:
    from shared.config import read_config_file

    body = read_config_file(ROOT / "configs" / "fig8" / "sparse-cen-macb.yaml")
    body.update(profile="thesis", interleave="lockstep", episodes=episodes,
                eval_every=EVAL_EVERY, eval_episodes=10, name="soak")  # fmt: skip
    return body


@pytest.mark.soak
@pytest.mark.timeout(int(MINUTES * 60 + 3 * 3600))
def test_a_group_at_thesis_settings_survives_random_faults(tmp_path):
    rng = random.Random(int(os.environ.get("MACB_SOAK_SEED", "0")))
    faults: list[dict] = []
    with Cluster(tmp_path, env=UP_ENV) as up:
        up.up(*UP, answering=SERVICES)
        from shared.config import make_config

        base = {k: v for k, v in soak_body(1).items() if k not in ("seeds", "name")}
        length = make_config(base).episode_len
        # sized to outlast the faults at ~25 group steps/s (the run goes on after them)
        episodes = int(MINUTES * 60 * 30 / length) // EVAL_EVERY * EVAL_EVERY + EVAL_EVERY
        r = httpx.post(f"{up.url}/experiments", json=soak_body(episodes), timeout=10)
        assert r.status_code in (200, 201), r.text
        exp = r.json()
        ids = [run["id"] for run in exp["runs"]]
        wait_for(lambda: up.points(ids[0]) >= 1, timeout=600, what="the group's first point")
        t_end = time.monotonic() + MINUTES * 60
        doubles = sorted(rng.sample(range(3, 12), 2))  # which faults hit two services
        n = 0
        while time.monotonic() < t_end:
            time.sleep(rng.uniform(10, 60))
            if time.monotonic() >= t_end or up.ended(*ids):
                break
            victims = rng.sample(VICTIMS, 2 if n in doubles else 1)
            kind = rng.choice(["SIGKILL", "SIGSTOP"])
            at = max(up.points(i) for i in ids)
            t0 = time.monotonic()
            if kind == "SIGKILL":
                for v in victims:
                    up.kill(v)
                paused = 0.0
            else:
                paused = rng.uniform(1, 15)
                up.pause(*victims, seconds=paused)
            fault = {"t": round(t0 - (t_end - MINUTES * 60), 1), "kind": kind,
                     "victims": victims, "paused_s": round(paused, 1)}  # fmt: skip
            try:
                wait_for(lambda at=at: max(up.points(i) for i in ids) > at, timeout=300,
                         what=f"a point after {kind} {victims}")  # fmt: skip
                fault["recovery_s"] = round(time.monotonic() - t0, 1)
            except AssertionError:
                fault["recovery_s"] = None
                faults.append(fault)
                raise
            faults.append(fault)
            print(json.dumps(fault), flush=True)
            n += 1
        wait_for(lambda: up.ended(*ids), timeout=3 * 3600, interval=5, what="the group's end")
        runs = [_check(up, run_id, episodes) for run_id in ids]
        result = {"minutes": MINUTES, "episodes": episodes, "faults": faults,
                  "runs": runs, "restarts": up.restarts()}  # fmt: skip
        (tmp_path / "soak.json").write_text(json.dumps(result, indent=1))
        print(json.dumps(result, indent=1))
        assert any(len(f["victims"]) == 2 for f in faults) or MINUTES < 5


def _check(up: Cluster, run_id: str, episodes: int) -> dict:
    run = assert_exact(up.finished(run_id), faults="restarted").record
    services = run["services"]
    learner, counter = services[run["assign"]["learner"]], services[run["assign"]["counter"]]
    return {"id": run_id, "counted": counter["counted_transitions"],
            "ingested": learner["ingested"], "updates": learner["updates"],
            "replay_ratio": learner["replay_ratio"], "points": episodes // EVAL_EVERY,
            "gaps": counter.get("gaps"), "duplicates": counter.get("duplicates"),
            "reason": run["reason"]}  # fmt: skip
