"""`interleave: lockstep`: a cluster run is `macb train`'s run, bit for bit.

Real services (router, counter, learner, evaluator, one actor) over loopback Zenoh.
The actor asks the learner for each step's action; the learner answers only once every
earlier step is counted, in replay and learnt, with its own `act`. Every metric row's
columns that the one-process trainer writes, timing aside, must then equal the
trainer's exactly: success, returns, counts, bonus diagnostics, update counts.
"""

from __future__ import annotations

import math

import pytest

from shared.config import make_config
from shared.control import start_run
from shared.trainer import train
from tests.test_services_run import check_exact, start_cluster, wait_services

TIMING = {"steps_per_sec", "train_steps_per_sec", "wall_s"}

BASE = {
    "episodes": 12,
    "episode_len": 10,
    "eval_every": 3,
    "eval_episodes": 4,
    "learning_starts": 30,
    "batch_size": 16,
    "hidden": [32, 32],
    "seed": 3,
    "learner_lanes": 1,
    "interleave": "lockstep",
}

CASES = {
    "simple-ddpg-constant": {"task": "simple", "algo": "ddpg", "explore": "constant"},
    "speaker_listener-cen-macb-thesis": {
        "task": "speaker_listener",
        "algo": "cen-maddpg",
        "explore": "cen-macb",
        "profile": "thesis",
        "k": 16,
    },
    "spread-dis-macb": {"task": "spread", "algo": "dis-maddpg", "explore": "dis-macb", "k": 8},
}


def same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def compare(cluster: list[dict], local: list[dict]) -> list[str]:
    """Every difference in the trainer's columns (timing aside), as text."""
    out = []
    if [r["episode"] for r in cluster] != [r["episode"] for r in local]:
        return [f"episodes {[r['episode'] for r in cluster]} vs {[r['episode'] for r in local]}"]
    for c, t in zip(cluster, local):
        for col in sorted(set(t) - TIMING):
            if col not in c:
                out.append(f"episode {t['episode']}: cluster row lacks {col}")
            elif not same(c[col], t[col]):
                out.append(f"episode {t['episode']} {col}: cluster {c[col]!r} local {t[col]!r}")
    return out


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_lockstep_cluster_run_is_the_trainers_run(procs, bus, tmp_path, case):
    config = make_config({**BASE, **CASES[case]})
    start_cluster(procs, tmp_path, 1)
    wait_services(bus, 4)
    watch = start_run(bus, config, actors=1)
    assert watch.wait(timeout=300) == "completed", watch.states
    check_exact(watch, [watch.assign["actors"][0]], config)
    learner = watch.states[watch.assign["learner"]]
    assert learner["policy_lag"] == 0.0
    cluster = sorted(watch.rows, key=lambda r: r["episode"])
    local = train(config, None, progress=False)
    diffs = compare(cluster, local)
    assert not diffs, "\n".join(diffs[:20])


def test_the_comparison_sees_one_changed_value():
    """The check above fails on a single differing value in any compared column."""
    rows = [{"episode": 3, "success_rate": 0.5, "bonus_mean": 0.25, "wall_s": 1.0}]
    assert compare(rows, [dict(rows[0])]) == []
    assert compare(rows, [{**rows[0], "wall_s": 2.0}]) == []  # timing aside
    assert compare(rows, [{**rows[0], "bonus_mean": 0.25000001}])
    assert compare([{"episode": 3, "wall_s": 1.0}], rows)  # a column missing
