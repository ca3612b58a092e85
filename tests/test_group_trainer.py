"""A run in a group gives the metric rows it gives alone.

`train_group` trains several runs of one task and network shape as one (shared/
group_trainer.py); each run's rows are compared with `train` of the same config alone
(fp32, one torch thread, `learner_lanes: 1`), every column but the timing ones, over
several evaluation points, in profile mpe2 and profile thesis (one minibatch per
agent, success as a terminal, random warm-up) and with arms that differ in exploration,
beta, k, reward, seed and count store (a count-min sketch or the exact table). A group
stopped between cuts resumes to the same rows."""

from __future__ import annotations

import json

import pytest

from cli.trainer import train, train_group
from shared.config import make_config
from shared.groups import check_group, form_groups

TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")

BASE = {
    "hidden": [32, 32],
    "episodes": 6,
    "eval_every": 2,
    "eval_episodes": 4,
    "learning_starts": 40,
    "batch_size": 16,
    "learner_lanes": 1,
    "threads": 1,
}


def cfgs_of(common: dict, arms: list[dict]):
    return [make_config({**BASE, **common, **arm}) for arm in arms]


def strip(rows):
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


GROUPS = {
    "speaker_listener-mpe2": (
        {"task": "speaker_listener", "algo": "cen-maddpg", "k": 16},
        [
            {"explore": "cen-macb", "seed": 0},
            {"explore": "cen-macb", "seed": 1, "beta": 0.4},
            {"explore": "dis-macb", "seed": 2},
            {"explore": "none", "seed": 3, "reward": "dense"},
        ],
    ),
    "speaker_listener-thesis": (
        {"task": "speaker_listener", "algo": "cen-maddpg", "profile": "thesis", "k": 16},
        [
            {"explore": "cen-macb", "seed": 0},
            {"explore": "constant", "seed": 1},
            {"explore": "none", "seed": 2},
        ],
    ),
    "simple-ddpg": (
        {"task": "simple", "algo": "ddpg", "explore": "dis-macb", "k": 8},
        [
            {"beta": 0.0, "seed": 0},
            {"beta": 1.2, "seed": 0},
            {"explore": "constant", "seed": 4},
            {"bonus_at": "collection", "hash": "raw", "key": "state", "seed": 7},
            {"bonus_at": "collection", "hash": "none", "seed": 8},
        ],
    ),
    # beta schedules (beyond the thesis): priced per run at its own transitions' beta
    "simple-scheduled-beta": (
        {"task": "simple", "algo": "ddpg", "explore": "dis-macb", "k": 8},
        [
            {"beta_schedule": {"kind": "linear", "end": 0.1, "horizon": 4}, "seed": 0},
            {
                "explore": "constant",
                "beta_schedule": {
                    "kind": "exponential",
                    "end": 0.05,
                    "horizon": 90,
                    "unit": "steps",
                },
                "seed": 1,
            },
            {
                "bonus_at": "collection",
                "hash": "raw",
                "beta_schedule": {"kind": "linear", "end": 2.0, "horizon": 70, "unit": "steps"},
                "seed": 2,
            },
            {"seed": 3},
        ],
    ),
    "speaker_listener-sketch": (  # count_sketch (tests/test_sketch.py) beside an exact table
        {"task": "speaker_listener", "algo": "cen-maddpg", "k": 16},
        [
            {"explore": "cen-macb", "seed": 0, "count_sketch": {"width": 64, "depth": 3}},
            {"explore": "dis-macb", "seed": 1, "count_sketch": {"memory_mb": 0.001}},
            {"explore": "cen-macb", "seed": 2},
        ],
    ),
    "spread-thesis": (
        {"task": "spread", "algo": "dis-maddpg", "profile": "thesis", "agents": 2},
        [{"explore": "dis-macb", "k": 8, "seed": 5}, {"explore": "none", "seed": 6}],
    ),
}


@pytest.mark.parametrize("name", list(GROUPS))
def test_each_run_of_a_group_gives_its_rows_alone(name, tmp_path):
    common, arms = GROUPS[name]
    cfgs = cfgs_of(common, arms)
    outs = [tmp_path / f"group-{r}" for r in range(len(cfgs))]
    grouped = train_group(cfgs, outs, progress=False)
    for r, cfg in enumerate(cfgs):
        alone = train(cfg, tmp_path / f"alone-{r}", progress=False)
        assert len(grouped[r]) == 3
        assert strip(grouped[r]) == strip(alone), f"run {r} ({arms[r]}) differs"
        written = [json.loads(x) for x in (outs[r] / "metrics.jsonl").read_text().splitlines()]
        assert strip(written) == strip(alone)
        assert (outs[r] / "checkpoint.pt").exists() and (outs[r] / "provenance.json").exists()


class Stop(Exception):
    pass


def test_a_stopped_group_resumes_to_the_same_rows(tmp_path):
    common, arms = GROUPS["speaker_listener-thesis"]
    cfgs = cfgs_of(common, arms)
    straight = train_group(cfgs, [tmp_path / f"a{r}" for r in range(3)], progress=False)
    outs = [tmp_path / f"b{r}" for r in range(3)]

    def stop_at_4(r, row):
        if row["episode"] == 4:
            raise Stop

    with pytest.raises(Stop):  # the cut of episode 4 is not written: resume from 2
        train_group(cfgs, outs, progress=False, on_metrics=stop_at_4, cut_every_s=0.0)
    resumed = train_group(cfgs, outs, progress=False, resume=True, cut_every_s=0.0)
    for r in range(3):
        assert strip(resumed[r]) == strip(straight[r])
        starts = json.loads((outs[r] / "provenance.json").read_text())["starts"]
        assert len(starts) == 2 and starts[0]["role"] == "group"


def test_a_group_cut_resumes_alone(tmp_path):
    """Each run's cut is a `macb train` cut: one run of a stopped group continues alone."""
    common, arms = GROUPS["simple-ddpg"]
    cfgs = cfgs_of(common, arms)
    outs = [tmp_path / f"g{r}" for r in range(len(cfgs))]

    def stop_at_4(r, row):
        if row["episode"] == 4:
            raise Stop

    with pytest.raises(Stop):
        train_group(cfgs, outs, progress=False, on_metrics=stop_at_4, cut_every_s=0.0)
    for r in (1, 4):  # 4 stores its bonuses with the replay rows
        alone = train(cfgs[r], outs[r], progress=False, resume=True)
        assert strip(alone) == strip(train(cfgs[r], tmp_path / f"straight{r}", progress=False))


def test_groups_are_formed_and_refused_by_what_runs_share():
    a = make_config({**BASE, "task": "simple", "algo": "ddpg", "seed": 1})
    b = make_config({**BASE, "task": "simple", "algo": "ddpg", "beta": 0.2})
    c = make_config({**BASE, "task": "simple", "algo": "ddpg", "batch_size": 32})
    assert form_groups([a, b, c]) == [[0, 1], [2]]
    assert form_groups([a, b, a], max_runs=2) == [[0, 1], [2]]
    with pytest.raises(ValueError, match="batch_size"):
        check_group([a, c])
    ref = make_config({**BASE, "task": "simple", "algo": "ddpg", "learner_impl": "reference"})
    with pytest.raises(ValueError, match="learner_impl reference"):
        check_group([a, ref])


def test_every_run_of_a_group_has_a_folder_or_none(tmp_path):
    from cli.trainer import GroupRun

    a = make_config({**BASE, "task": "simple", "algo": "ddpg"})
    with pytest.raises(ValueError, match="every run of a group an output folder, or none"):
        GroupRun([a, a], [tmp_path / "x", None], 60.0)


def test_a_group_of_one_shares_the_group_learner_and_train_keeps_its_own():
    """`learner_lanes: auto` (the default) picks its lanes by timing, so a `--local` run
    grouped alone must update as a group does (its resume is then exact); `macb train`
    keeps the learner its config asks for."""
    from cli.trainer import GroupRun
    from shared.core.learners import TunedMADDPG
    from shared.core.learners.group import GroupMADDPG
    from shared.core.learners.runs import SoloRuns

    cfg = make_config({"task": "simple", "algo": "ddpg", "episodes": 2})
    assert cfg.learner_lanes == "auto"
    assert isinstance(GroupRun([cfg], [None], 60.0).learner, GroupMADDPG)
    own = GroupRun([cfg], [None], 60.0, own_learner=True).learner
    assert isinstance(own, SoloRuns) and isinstance(own.learner, TunedMADDPG)


# A group mixing every kind of arm (exact, sketch, priced at collection, scheduled beta,
# constant, none) and a run its early_stop rule ends after its second point.
DEVICE_ARMS = [
    {"explore": "cen-macb", "seed": 0},
    {"explore": "dis-macb", "seed": 1, "count_sketch": {"width": 64, "depth": 3}},
    {"explore": "cen-macb", "bonus_at": "collection", "hash": "raw", "seed": 2},
    {"explore": "cen-macb", "seed": 3,
     "beta_schedule": {"kind": "linear", "end": 0.1, "horizon": 90, "unit": "steps"}},
    {"explore": "constant", "seed": 4},
    {"explore": "none", "seed": 5, "buffer_size": 100},
    {"explore": "cen-macb", "seed": 6,
     "early_stop": {"rule": "no_improvement", "patience": 1, "min_delta": 1.0}},
]  # fmt: skip


def train_with(cfgs, outs, backend, resume=False, on_metrics=None, cut_every_s=60.0):
    """`train_group`'s loop with the replay's backend forced (torch: the device path,
    on CPU tensors here)."""
    from cli.trainer import GroupRun

    group = GroupRun(cfgs, outs, cut_every_s, replay_backend=backend)
    if resume:
        group.restore()
    return group, group.go(False, on_metrics)


@pytest.mark.parametrize("profile", ["mpe2", "thesis"])
def test_a_group_with_its_replay_on_a_device_trains_the_hosts_rows(profile, tmp_path):
    """The replay's device path (tensors, one copy a step in, gathered there) trains
    every run to the rows the host's arrays give, bit for bit (fp32, CPU), a wrapping
    buffer and a run stopped by its rule among them; stopped and resumed from a cut,
    the device path refills its replay to the same rows again."""
    common = {"task": "speaker_listener", "algo": "cen-maddpg", "k": 16, "profile": profile}
    cfgs = cfgs_of(common, DEVICE_ARMS)
    outs = lambda name: [tmp_path / f"{name}{r}" for r in range(len(cfgs))]  # noqa: E731
    _, host = train_with(cfgs, outs("host"), None)
    group, dev = train_with(cfgs, outs("dev"), "torch")
    assert group.replay.backend == "torch" and group.members[-1].stopped is not None
    assert group.members[-1].frozen_draws is not None  # its fixed draw, gathered there
    assert [len(rows) for rows in host] == [3, 3, 3, 3, 3, 3, 2]
    for r in range(len(cfgs)):
        assert strip(dev[r]) == strip(host[r]), f"run {r} ({DEVICE_ARMS[r]}) differs"

    def stop_at_4(r, row):
        if row["episode"] == 4:
            raise Stop

    with pytest.raises(Stop):
        train_with(cfgs, outs("cut"), "torch", on_metrics=stop_at_4, cut_every_s=0.0)
    _, resumed = train_with(cfgs, outs("cut"), "torch", resume=True, cut_every_s=0.0)
    for r in range(len(cfgs)):
        assert strip(resumed[r]) == strip(host[r]), f"run {r} resumed"


def test_a_reference_run_in_a_local_figure_trains_alone_with_its_own_learner(tmp_path):
    """A run asking for the reference learner (the batched one's CPU definition) is not
    put in a group beside batched runs, which would refuse them all: `--local` trains it
    alone with its own learner, `macb train`'s rows, and the others as a group."""
    from cli.local import LocalRun, run_groups, run_rows

    common = {**BASE, "task": "simple", "algo": "ddpg", "explore": "dis-macb"}
    cfgs = [
        make_config({**common, "seed": 1}),
        make_config({**common, "seed": 2, "learner_impl": "reference"}),
        make_config({**common, "seed": 3}),
    ]
    assert form_groups(cfgs) == [[0, 2], [1]]
    runs = [LocalRun(f"r{i}", None, c.seed, c) for i, c in enumerate(cfgs)]
    assert run_groups(runs, tmp_path / "runs", quiet=True, jobs=1) == 0
    ref = train(cfgs[1], tmp_path / "alone", progress=False)
    assert strip(run_rows(tmp_path / "runs" / "r1")) == strip(ref)
    group = train_group([cfgs[0], cfgs[2]], [None, None], progress=False)
    for r, rows in zip((0, 2), group):
        assert strip(run_rows(tmp_path / "runs" / f"r{r}")) == strip(rows)
