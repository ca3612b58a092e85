"""`interleave: lockstep`: a cluster run is `macb train`'s run, bit for bit.

Real services (router, counter, learner, evaluator, one actor) over loopback Zenoh.
The actor asks the learner for each step's action; the learner answers only once every
earlier step is counted, in replay and learnt, with its own `act`. Every metric row's
columns that the one-process trainer writes, timing aside, must then equal the
trainer's exactly (success, returns, counts, bonus diagnostics, update counts), and so
must the learner's final state: every weight, target, Adam moment and step count.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from cli.trainer import train
from shared.config import make_config
from shared.net.control import start_run
from tests.harness import assert_exact, wait_for, wait_services

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
    # dense: the evaluation returns follow every weight (sparse ones stay -10 this early)
    "simple-ddpg-constant": {
        "task": "simple",
        "algo": "ddpg",
        "explore": "constant",
        "reward": "dense",
    },
    "speaker_listener-cen-macb-thesis": {
        "task": "speaker_listener",
        "algo": "cen-maddpg",
        "explore": "cen-macb",
        "profile": "thesis",
        "k": 16,
    },
    "spread-dis-macb": {"task": "spread", "algo": "dis-maddpg", "explore": "dis-macb", "k": 8},
    # beta schedules (beyond the thesis): the learner prices the counter's counts at the
    # beta of the transition each update is owed for, as macb train does
    "speaker_listener-cen-macb-linear-beta": {
        "task": "speaker_listener",
        "algo": "cen-maddpg",
        "explore": "cen-macb",
        "profile": "thesis",
        "k": 16,
        "beta_schedule": {"kind": "linear", "end": 0.1, "horizon": 8},
    },
    "simple-ddpg-constant-exponential-beta": {
        "task": "simple",
        "algo": "ddpg",
        "explore": "constant",
        "reward": "dense",
        "beta_schedule": {"kind": "exponential", "end": 0.05, "horizon": 90, "unit": "steps"},
    },
    # counts in a count-min sketch small enough to collide (shared/core/counting.py)
    "speaker_listener-cen-macb-thesis-sketch": {
        "task": "speaker_listener",
        "algo": "cen-maddpg",
        "explore": "cen-macb",
        "profile": "thesis",
        "k": 16,
        "count_sketch": {"width": 64, "depth": 3},
    },
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


def state_differences(a, b, where: str = "") -> list[str]:
    """Every tensor or value of two learner state dicts that is not equal, bit for bit."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{where}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in state_differences(a[k], b[k], f"{where}/{k}")]
    if isinstance(a, list | tuple) and isinstance(b, list | tuple) and len(a) == len(b):
        return [
            d for i, (x, y) in enumerate(zip(a, b)) for d in state_differences(x, y, f"{where}/{i}")
        ]
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return [] if a.dtype == b.dtype and torch.equal(a, b) else [where]
    return [] if a == b else [f"{where}: {a!r} != {b!r}"]


def learner_states(data: Path, run: str, config, local: Path) -> tuple[dict, dict, list[dict]]:
    """The cluster learner's final state, the trainer's, and the trainer's rows."""
    rows = train(config, local, progress=False)
    cluster = torch.load(data / "learner" / run / "checkpoint.pt", weights_only=True)
    mine = torch.load(local / "checkpoint.pt", weights_only=True)
    return cluster["learner"], mine["learner"], rows


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_lockstep_cluster_run_is_the_trainers_run(cluster, bus, tmp_path, case):
    config = make_config({**BASE, **CASES[case]})
    cluster.services(1)
    wait_services(bus, 4)
    watch = start_run(bus, config, actors=1)
    assert watch.wait(timeout=300) == "completed", watch.states
    learner = assert_exact(watch, config).learner
    assert learner["policy_lag"] == 0.0
    states = learner_states(cluster.data, watch.run, config, tmp_path / "l")
    cluster_state, local_state, local = states
    rows = sorted(watch.rows, key=lambda r: r["episode"])
    diffs = compare(rows, local)
    assert not diffs, "\n".join(diffs[:20])
    diffs = state_differences(cluster_state, local_state)
    assert not diffs, diffs[:20]


def test_the_comparison_sees_one_changed_value():
    """The check above fails on a single differing value in any compared column."""
    rows = [{"episode": 3, "success_rate": 0.5, "bonus_mean": 0.25, "wall_s": 1.0}]
    assert compare(rows, [dict(rows[0])]) == []
    assert compare(rows, [{**rows[0], "wall_s": 2.0}]) == []  # timing aside
    assert compare(rows, [{**rows[0], "bonus_mean": 0.25000001}])
    assert compare([{"episode": 3, "wall_s": 1.0}], rows)  # a column missing


@pytest.mark.parametrize(
    "rule",
    [
        {"rule": "success_at_least", "threshold": 0.0, "patience": 2},  # at episode 6
        {"rule": "no_improvement", "patience": 2, "min_delta": 1.0},  # at episode 9
    ],
)
def test_a_lockstep_run_stopped_by_its_rule_is_the_trainers_run(cluster, bus, tmp_path, rule):
    """`early_stop` (beyond the thesis): the learner holds each step after a point until
    the point's row is in; the evaluator reads the rule on its rows, and the run ends
    completed where `macb train` ends it, its rows (the reason on the last) and final
    learner state the trainer's, its actor and counter at that episode."""
    case = {**CASES["speaker_listener-cen-macb-linear-beta"], "early_stop": rule}
    config = make_config({**BASE, **case})
    cluster.services(1)
    wait_services(bus, 4)
    watch = start_run(bus, config, actors=1)
    assert watch.wait(timeout=300) == "completed", watch.states
    assert_exact(watch, config)
    cluster_state, local_state, local = learner_states(cluster.data, watch.run, config, tmp_path)
    rows = sorted(watch.rows, key=lambda r: r["episode"])
    assert rows[-1]["episode"] == local[-1]["episode"] < config.episodes
    assert rows[-1]["stop_reason"] == local[-1]["stop_reason"]
    assert rows[-1]["stop_reason"].startswith(f"early_stop {rule['rule']}")
    assert watch.decision().reason == rows[-1]["stop_reason"]
    diffs = compare(rows, local)
    assert not diffs, "\n".join(diffs[:20])
    diffs = state_differences(cluster_state, local_state)
    assert not diffs, diffs[:20]
    assert_same_best(cluster.data / "learner" / watch.run, tmp_path, local)


def assert_same_best(cluster_folder: Path, local_folder: Path, rows: list[dict]) -> None:
    """The cluster learner's best.pt is the trainer's: the point with the highest
    success (the earliest of equals), every tensor equal; and not the last point's
    learner when the best point came before it."""
    theirs = torch.load(cluster_folder / "best.pt", weights_only=True)
    mine = torch.load(local_folder / "best.pt", weights_only=True)
    top = max(row["success_rate"] for row in rows)
    best = next(row for row in rows if row["success_rate"] == top)
    assert theirs["kind"] == mine["kind"] == "best"
    assert theirs["counters"] == mine["counters"]
    assert mine["counters"]["episode"] == best["episode"]
    diffs = state_differences(theirs["learner"], mine["learner"])
    assert not diffs, diffs[:20]
    last = torch.load(cluster_folder / "checkpoint.pt", weights_only=True)["learner"]
    assert bool(state_differences(theirs["learner"], last)) == (best is not rows[-1])


def test_early_stop_under_async_is_refused_and_a_cluster_group_may_hold_it():
    from services.learner.state import open_error

    config = make_config({**BASE, "early_stop": {"rule": "no_improvement"}})
    assert open_error(config, 1) is None
    run_async = config.model_copy(update={"interleave": "async"})
    assert "not interleave async" in (open_error(run_async, 2) or "")
    # the API's planner and start_group form cluster groups of such runs (they go on
    # without a run its rule ended: the group test below)
    from shared.groups import group_error

    assert group_error([config, config.model_copy(update={"early_stop": None})], 1) is None


# The counter's resend (3 s) in `make test`; the short pauses in test-slow, since the
# group's test below pauses each service in `make test` (a run alone is a group of one).
@pytest.mark.parametrize(
    ("paused", "seconds"),
    [
        pytest.param("counter", 1.2, marks=pytest.mark.slow),
        ("counter", 3.0),
        pytest.param("learner", 1.2, marks=pytest.mark.slow),
        pytest.param("actor0", 1.2, marks=pytest.mark.slow),
    ],
)
def test_a_late_count_or_a_late_message_changes_nothing(cluster, bus, tmp_path, paused, seconds):
    """One service paused mid-run (SIGSTOP, then SIGCONT): the counter's acks come late
    (3 s: the actor sends the step again meanwhile, which the counter then ignores), or
    the learner's answers (the actor sends its request again meanwhile, and the learner
    answers the repeat with the same action), or the actor's next step. Lockstep waits
    for each, so the run is still `macb train`'s bit for bit; a learner that acted
    before a count arrived would not be."""
    config = make_config({**BASE, **CASES["speaker_listener-cen-macb-thesis"], "episodes": 24})
    cluster.services(1)
    wait_services(bus, 4)
    watch = start_run(bus, config, actors=1)
    wait_for(lambda: len(watch.rows) >= 1, timeout=120, what="the first point")
    cluster.pause(paused, seconds=seconds)
    assert watch.wait(timeout=300) == "completed", watch.states
    assert watch.rows[-1]["episode"] == 24 and len(watch.rows) == 8
    states = learner_states(cluster.data, watch.run, config, tmp_path / "l")
    cluster_state, local_state, local = states
    diffs = compare(sorted(watch.rows, key=lambda r: r["episode"]), local)
    learner = watch.states[watch.assign.learner]
    said = f"bonus failures {learner['bonus_failures']}, unanswered {learner['bonus_unanswered']}"
    assert not diffs, "\n".join([said] + diffs[:20])
    assert not state_differences(cluster_state, local_state)


def test_the_asynchronous_interleave_is_another_run(cluster, bus, tmp_path):
    """The comparison sees interleaving: the same config with `interleave: async` (one
    actor collecting whole episodes with weights published at episode ends) does not
    give the trainer's rows."""
    config = make_config({**BASE, **CASES["simple-ddpg-constant"], "interleave": "async"})
    cluster.services(1)
    wait_services(bus, 4)
    watch = start_run(bus, config, actors=1)
    assert watch.wait(timeout=300) == "completed", watch.states
    states = learner_states(cluster.data, watch.run, config, tmp_path / "l")
    cluster_state, local_state, local = states
    rows = sorted(watch.rows, key=lambda r: r["episode"])
    assert compare(rows, local)
    assert state_differences(cluster_state, local_state)


def test_lockstep_with_several_actors_is_refused_before_it_starts():
    from services.api.schemas import ExperimentCreate

    body = {**BASE, **CASES["simple-ddpg-constant"], "actors": 2}
    with pytest.raises(ValueError, match="actors: interleave lockstep"):
        ExperimentCreate.model_validate(body)
    ExperimentCreate.model_validate({**body, "interleave": "async"})
    thesis = {"task": "simple", "algo": "ddpg", "profile": "thesis", "actors": 2}
    with pytest.raises(ValueError, match="runs one actor"):  # the profile's default
        ExperimentCreate.model_validate(thesis)
    with pytest.raises(ValueError, match="runs one actor"):
        config = make_config({**BASE, **CASES["simple-ddpg-constant"]})
        start_run(None, config, actors=2)  # type: ignore[arg-type]


GROUP = [  # one group: seeds and the exploration differ, task and networks are shared
    {**BASE, **CASES["speaker_listener-cen-macb-thesis"], "seed": 3},
    {**BASE, **CASES["speaker_listener-cen-macb-thesis"], "seed": 4, "beta": 0.4},
    {**BASE, **CASES["speaker_listener-cen-macb-thesis"], "seed": 5, "explore": "constant"},
]
# and a run counting in a count-min sketch, in the group test below
SKETCH_RUN = {**BASE, **CASES["speaker_listener-cen-macb-thesis-sketch"], "seed": 6}


def test_a_lockstep_cluster_group_is_the_group_trainers_runs(cluster, bus, tmp_path):
    """A group of 4 runs (one counting in a count-min sketch) served by one learner
    (GroupMADDPG), one actor (a VecTask of their worlds, one act request per step) and one
    evaluator: each run's rows and final learner state are those the one-process group
    gives it (and so `macb train`'s)."""
    from cli.trainer import train_group
    from shared.net.control import start_group

    configs = [make_config(c) for c in [*GROUP, SKETCH_RUN]]
    cluster.services(1)
    wait_services(bus, 4)
    watches = start_group(bus, configs, runs=[f"g{r}" for r in range(len(configs))])
    for watch in watches:
        assert watch.wait(timeout=300) == "completed", watch.states
    outs = [tmp_path / f"local{r}" for r in range(len(configs))]
    local = train_group(configs, outs, progress=False)
    for r, (watch, config) in enumerate(zip(watches, configs)):
        learner = assert_exact(watch, config).learner
        assert learner["policy_lag"] == 0.0
        diffs = compare(sorted(watch.rows, key=lambda row: row["episode"]), local[r])
        assert not diffs, f"run {r}\n" + "\n".join(diffs[:20])
        theirs = torch.load(
            cluster.data / "learner" / watch.run / "checkpoint.pt", weights_only=True
        )
        mine = torch.load(outs[r] / "checkpoint.pt", weights_only=True)
        diffs = state_differences(theirs["learner"], mine["learner"])
        assert not diffs, (r, diffs[:20])


def test_a_lockstep_cluster_group_with_scheduled_betas_is_the_group_trainers_runs(
    cluster, bus, tmp_path
):
    """`beta_schedule` in a cluster group: each run prices at its own schedule's beta
    (the control too), and its rows, `beta` column included, and final learner state are
    the one-process group's."""
    from cli.trainer import train_group
    from shared.net.control import start_group

    linear = {"kind": "linear", "end": 0.1, "horizon": 8}
    steps = {"kind": "exponential", "end": 0.05, "horizon": 90, "unit": "steps"}
    configs = [
        make_config({**GROUP[0], "beta_schedule": linear}),
        make_config({**GROUP[2], "beta_schedule": steps}),
    ]
    cluster.services(1)
    wait_services(bus, 4)
    watches = start_group(bus, configs, runs=["b0", "b1"])
    for watch in watches:
        assert watch.wait(timeout=300) == "completed", watch.states
    outs = [tmp_path / f"local{r}" for r in range(2)]
    local = train_group(configs, outs, progress=False)
    for r, watch in enumerate(watches):
        rows = sorted(watch.rows, key=lambda row: row["episode"])
        assert [row["beta"] for row in rows] == [row["beta"] for row in local[r]]
        assert rows[-1]["beta"] < rows[0]["beta"]
        diffs = compare(rows, local[r])
        assert not diffs, f"run {r}\n" + "\n".join(diffs[:20])
        theirs = torch.load(
            cluster.data / "learner" / watch.run / "checkpoint.pt", weights_only=True
        )
        mine = torch.load(outs[r] / "checkpoint.pt", weights_only=True)
        diffs = state_differences(theirs["learner"], mine["learner"])
        assert not diffs, (r, diffs[:20])


@pytest.mark.parametrize("paused", ["counter", "learner", "actor0", "evaluator"])
def test_a_late_count_or_message_changes_no_run_of_a_group(cluster, bus, tmp_path, paused):
    """As for a run alone: one service of a group paused 3 s mid-run (its acks, answers,
    steps or rows come late) and every run is still the one-process group's."""
    from cli.trainer import train_group
    from shared.net.control import start_group

    configs = [make_config({**c, "episodes": 24}) for c in GROUP]
    cluster.services(1)
    wait_services(bus, 4)
    watches = start_group(bus, configs, runs=[f"p{r}" for r in range(3)])
    wait_for(lambda: len(watches[0].rows) >= 1, timeout=120, what="the first point")
    cluster.pause(paused, seconds=3.0)
    for watch in watches:
        assert watch.wait(timeout=300) == "completed", watch.states
    local = train_group(configs, [tmp_path / f"l{r}" for r in range(3)], progress=False)
    for r, watch in enumerate(watches):
        diffs = compare(sorted(watch.rows, key=lambda row: row["episode"]), local[r])
        assert not diffs, f"run {r}\n" + "\n".join(diffs[:20])


def test_a_cluster_group_goes_on_when_its_rule_ends_one_run(cluster, bus, tmp_path):
    """`early_stop` in a cluster group of 3: the lead run's rule ends it at episode 6
    and the last run's at 9; each completes there with its reason (learner, actor,
    evaluator and counter follow it) while the others go on, and every run's rows are
    `macb train`'s for that run (the stopped runs' reasons included), its final learner
    and best.pt the trainer's, tensor for tensor."""
    from cli.trainer import train_group
    from shared.net.control import start_group

    at_least = {"rule": "success_at_least", "threshold": 0.0, "patience": 2}  # at episode 6
    flat = {"rule": "no_improvement", "patience": 2, "min_delta": 1.0}  # at episode 9
    configs = [
        make_config({**GROUP[0], "early_stop": at_least}),
        make_config(GROUP[1]),
        make_config({**GROUP[2], "early_stop": flat}),
    ]
    cluster.services(1)
    wait_services(bus, 4)
    watches = start_group(bus, configs, runs=["s0", "s1", "s2"])
    for watch in watches:
        assert watch.wait(timeout=300) == "completed", watch.states
    outs = [tmp_path / f"alone{r}" for r in range(3)]
    alone = [train(c, out, progress=False) for c, out in zip(configs, outs)]
    group = train_group(configs, [tmp_path / f"group{r}" for r in range(3)], progress=False)
    assert [rows[-1]["episode"] for rows in alone] == [6, 12, 9]
    for r, (watch, config) in enumerate(zip(watches, configs)):
        assert_exact(watch, config)
        rows = sorted(watch.rows, key=lambda row: row["episode"])
        for local in (alone[r], group[r]):
            diffs = compare(rows, local)
            assert not diffs, f"run {r}\n" + "\n".join(diffs[:20])
        folder = cluster.data / "learner" / watch.run
        theirs = torch.load(folder / "checkpoint.pt", weights_only=True)
        mine = torch.load(outs[r] / "checkpoint.pt", weights_only=True)
        diffs = state_differences(theirs["learner"], mine["learner"])
        assert not diffs, (r, diffs[:20])
        if config.early_stop is None:
            assert "stop_reason" not in rows[-1] and not (folder / "best.pt").exists()
            continue
        assert rows[-1]["stop_reason"] == alone[r][-1]["stop_reason"]
        assert watch.decision().reason == rows[-1]["stop_reason"]
        assert_same_best(folder, outs[r], alone[r])


# Long enough that the other run is still going when the test has seen the lead's end
# (the group steps 100-200 steps a second here; ending the lead takes the watch longer
# under load than 12 more episodes take).
EPISODES_PAST_STOP = 48


# The learner in `make test`; the actor and the evaluator in test-slow.
@pytest.mark.parametrize(
    "victim",
    ["learner", *(pytest.param(v, marks=pytest.mark.slow) for v in ("actor0", "evaluator"))],
)
def test_a_cluster_group_goes_on_after_a_restart_past_one_runs_stop(cluster, bus, tmp_path, victim):
    """A service of the group killed (SIGKILL) and started again once the lead run's
    rule has ended it: the restarted learner serves the group with that run retired
    (its fixed update arrays; the other from its cut and log), the restarted actor steps
    its world unpublished, the restarted evaluator waits for none of its points. The
    other run completes exact in its counts (after a fault a lockstep run is not bit
    for bit `macb train`'s: docs/reliability.md) and the stopped run stays as it ended,
    its rows `macb train`'s."""
    from shared.net.control import start_group

    at_least = {"rule": "success_at_least", "threshold": 0.0, "patience": 2}  # at episode 6
    configs = [
        make_config({**GROUP[0], "early_stop": at_least, "episodes": EPISODES_PAST_STOP}),
        make_config({**GROUP[1], "episodes": EPISODES_PAST_STOP}),
    ]
    cut_each_s = {"MACB_LEARNER_CUT_S": "0.5"}  # (a resume from cuts, the retired run's too)
    for sid in ("counter", "learner", "evaluator", "actor0"):
        cluster.service(sid.rstrip("0"), sid, env=cut_each_s)
    wait_services(bus, 4)
    watches = start_group(bus, configs, runs=["k0", "k1"])
    assert watches[0].wait(timeout=300) == "completed", watches[0].states
    assert len(watches[1].rows) < EPISODES_PAST_STOP // 3, "the kill lands while the group goes on"
    cluster.kill(victim)
    cluster.service(victim.rstrip("0"), victim, name=f"{victim}-again", env=cut_each_s)
    assert watches[1].wait(timeout=300) == "completed", watches[1].states
    for watch, config in zip(watches, configs):
        assert_exact(watch, config, faults="restarted")
    stopped = sorted(watches[0].rows, key=lambda row: row["episode"])
    diffs = compare(stopped, train(configs[0], tmp_path / "alone", progress=False))
    assert not diffs, "\n".join(diffs[:20])
    assert watches[0].decision().reason == stopped[-1]["stop_reason"]
    assert [max(row["episode"] for row in w.rows) for w in watches] == [6, EPISODES_PAST_STOP]
    if victim == "learner":  # the group resumed whole, the stopped run retired in it
        assert "runs ['k0', 'k1'] resumed" in cluster.log("learner-again")
