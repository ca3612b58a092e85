"""`early_stop` (beyond the thesis: its §6.3 and §7 suggest early stopping for
Cen-MACB's fall after it converges): a run ends, completed, when its rule holds on its
evaluation points, with the reason on its last row, its best point's learner in best.pt
and its last in checkpoint.pt; in a group the other runs go on, their rows what they
give alone; a resumed group stops the run where it stopped."""

from __future__ import annotations

import json

import pytest
import torch

from cli.local import run_state
from cli.trainer import train, train_group
from shared.config import ConfigError, make_config
from shared.metrics import early_stop_reason
from shared.persist import checkpoint
from tests.test_lockstep import state_differences

TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")
BASE = {
    "task": "simple",
    "algo": "ddpg",
    "explore": "dis-macb",
    "hidden": [16, 16],
    "episodes": 10,
    "episode_len": 10,
    "eval_every": 2,
    "eval_episodes": 2,
    "learning_starts": 20,
    "batch_size": 8,
    "learner_lanes": 1,
    "k": 8,
}
# holds at the second point whatever the run learnt: episode 4
AT_4 = {"rule": "success_at_least", "threshold": 0.0, "patience": 2}


def strip(rows):
    return [{k: v for k, v in r.items() if k not in TIMING and k != "stop_reason"} for r in rows]


def rows_of(*success: float) -> list[dict]:
    return [{"episode": 10 * (i + 1), "success_rate": s} for i, s in enumerate(success)]


def test_the_rules_read_the_points_so_far():
    at_least = make_config({**BASE, "early_stop": {"rule": "success_at_least", "threshold": 0.8,
                                                   "patience": 2}}).early_stop  # fmt: skip
    assert early_stop_reason(at_least, rows_of(0.9)) is None  # one point of two
    assert early_stop_reason(at_least, rows_of(0.9, 0.7)) is None
    assert "at 2 point(s) in a row" in early_stop_reason(at_least, rows_of(0.7, 0.8, 0.9))
    smooth = at_least.model_copy(update={"smooth": 2, "patience": 1})
    assert early_stop_reason(smooth, rows_of(0.6, 0.9)) is None  # mean 0.75
    assert early_stop_reason(smooth, rows_of(0.7, 0.9)) is not None  # mean 0.8
    flat = make_config({**BASE, "early_stop": {"rule": "no_improvement", "patience": 2,
                                               "min_delta": 0.05}}).early_stop  # fmt: skip
    assert early_stop_reason(flat, rows_of(0.1, 0.5, 0.4)) is None  # best at 20, 1 point since
    why = early_stop_reason(flat, rows_of(0.1, 0.5, 0.4, 0.54))  # 0.54 is not 0.05 above
    assert why is not None and "not above 0.5 (episode 20) for 2 point(s)" in why
    assert early_stop_reason(flat, rows_of(0.1, 0.5, 0.4, 0.56)) is None
    assert early_stop_reason(None, rows_of(1.0)) is None


def test_a_mean_on_the_limit_is_on_it_not_a_rounding_below_or_above():
    """Means a person reads as equal are equal to the rules: a running float mean of
    0.7, 1.0, 1.0 is 0.8999999999999999 (the shipped remedies rule's threshold 0.9 held
    there), and 0.0, 0.2 then 0.2, 0.0 is no improvement (the sums' roundings differ)."""
    from shared.metrics import smoothed

    rule = {"rule": "success_at_least", "threshold": 0.9, "patience": 3, "smooth": 3}
    at_least = make_config({**BASE, "early_stop": rule}).early_stop
    rows = rows_of(0.1, 0.7, 1.0, 1.0, 0.7, 1.0)
    assert smoothed([r["success_rate"] for r in rows], 3)[-3:] != [0.9, 0.9, 0.9]  # the case
    assert "at 3 point(s) in a row" in (early_stop_reason(at_least, rows) or "")
    assert early_stop_reason(at_least, rows_of(0.1, 0.7, 1.0, 1.0, 0.7, 0.9)) is None
    rule = {"rule": "no_improvement", "patience": 2, "smooth": 2}
    flat = make_config({**BASE, "early_stop": rule}).early_stop
    why = early_stop_reason(flat, rows_of(0.0, 0.2, 0.0, 0.1))
    assert why is not None and "not above 0.1 (episode 20) for 2 point(s)" in why
    assert early_stop_reason(flat, rows_of(0.0, 0.2, 0.0, 0.3)) is None


@pytest.mark.parametrize(
    ("rule", "says"),
    [
        ({"rule": "success_at_least"}, "early_stop.threshold: rule success_at_least needs"),
        ({"rule": "success_at_least", "threshold": 1.5}, "early_stop.threshold: Input"),
        ({"rule": "no_improvement", "threshold": 0.5}, "early_stop.threshold: rule no_improvement"),
        ({"rule": "no_improvement", "patience": 0}, "early_stop.patience: Input"),
        ({"rule": "no_improvement", "smooth": 0}, "early_stop.smooth: Input"),
        ({"rule": "best"}, "early_stop.rule: Input should be"),
        ({"threshold": 0.5}, "early_stop.rule: Field required"),
        ({"rule": "no_improvement", "after": 3}, "early_stop.after: unknown key"),
    ],
)
def test_invalid_rules_are_refused_naming_the_field_and_the_reason(rule, says):
    with pytest.raises(ConfigError, match=says.replace(".", r"\.")):
        make_config({**BASE, "early_stop": rule})


def test_a_run_stops_by_its_rule_completed_keeping_its_best_and_last(tmp_path):
    full = train(make_config(BASE), tmp_path / "full", progress=False)
    cfg = make_config({**BASE, "early_stop": AT_4})
    rows = train(cfg, tmp_path / "stop", progress=False)
    assert [r["episode"] for r in rows] == [2, 4]
    assert strip(rows) == strip(full[:2])  # the rule ends the run, changing nothing before
    assert rows[0]["stop_reason"] is None and rows[1]["stop_reason"].startswith(
        "early_stop success_at_least"
    )
    written = [
        json.loads(x) for x in (tmp_path / "stop" / "metrics.jsonl").read_text().splitlines()
    ]
    assert written[-1]["stop_reason"] == rows[1]["stop_reason"]
    assert run_state(tmp_path / "stop", cfg) == "done"  # completed, not cut short
    # the last weights are those a 4-episode run ends with, bit for bit
    four = make_config({**BASE, "episodes": 4})
    train(four, tmp_path / "four", progress=False)
    last = checkpoint.load(tmp_path / "stop" / "checkpoint.pt", "final")
    theirs = checkpoint.load(tmp_path / "four" / "checkpoint.pt", "final")
    assert not state_differences(last["learner"], theirs["learner"])
    assert last["counters"]["episodes"] == 4
    # best.pt: the best point (the earliest of equals), plain tensors (weights_only)
    best = checkpoint.load(tmp_path / "stop" / "best.pt", "best")
    top = max(r["success_rate"] for r in rows)
    first = next(r for r in rows if r["success_rate"] == top)
    assert best["counters"]["episode"] == first["episode"]
    assert best["counters"]["success_rate"] == top and "tables" not in best
    torch.load(tmp_path / "stop" / "best.pt", weights_only=True)


def test_without_the_key_nothing_is_written_beside(tmp_path):
    rows = train(make_config({**BASE, "episodes": 4}), tmp_path, progress=False)
    assert not (tmp_path / "best.pt").exists() and "stop_reason" not in rows[0]
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0]
    assert "stop_reason" not in header
    stopped = make_config({**BASE, "early_stop": AT_4})
    train(stopped, tmp_path / "s", progress=False)
    assert (tmp_path / "s" / "metrics.csv").read_text().splitlines()[0].endswith(",stop_reason")


GROUP = [
    {**BASE, "seed": 1, "early_stop": AT_4},
    {**BASE, "seed": 2},
    {**BASE, "seed": 3, "explore": "constant",
     "early_stop": {"rule": "no_improvement", "patience": 3, "min_delta": 1.0}},  # episode 8
]  # fmt: skip


def test_a_group_goes_on_for_its_other_runs_when_one_stops(tmp_path):
    cfgs = [make_config(c) for c in GROUP]
    grouped = train_group(cfgs, [tmp_path / f"g{r}" for r in range(3)], progress=False)
    assert [len(rows) for rows in grouped] == [2, 5, 4]
    for r, cfg in enumerate(cfgs):
        alone = train(cfg, tmp_path / f"a{r}", progress=False)
        assert strip(grouped[r]) == strip(alone), r
        assert grouped[r][-1].get("stop_reason") == alone[-1].get("stop_reason")
    assert "no_improvement" in grouped[2][-1]["stop_reason"]
    assert run_state(tmp_path / "g0", cfgs[0]) == run_state(tmp_path / "g1", cfgs[1]) == "done"


class Stop(Exception):
    pass


def test_a_group_resumed_after_a_run_stopped_gives_the_same_rows(tmp_path):
    cfgs = [make_config(c) for c in GROUP]
    straight = train_group(cfgs, [tmp_path / f"s{r}" for r in range(3)], progress=False)
    outs = [tmp_path / f"b{r}" for r in range(3)]

    def stop_at_8(r, row):
        if row["episode"] == 8:
            raise Stop

    with pytest.raises(Stop):  # run 0 stopped at 4; the cut of 8 is written: resume from 8
        train_group(cfgs, outs, progress=False, on_metrics=stop_at_8, cut_every_s=0.0)
    resumed = train_group(cfgs, outs, progress=False, resume=True, cut_every_s=0.0)
    for r in range(3):
        assert strip(resumed[r]) == strip(straight[r]), r
        assert resumed[r][-1].get("stop_reason") == straight[r][-1].get("stop_reason")
    last = checkpoint.load(outs[0] / "checkpoint.pt", "final")
    theirs = checkpoint.load(tmp_path / "s0" / "checkpoint.pt", "final")
    assert not state_differences(last["learner"], theirs["learner"])


def test_both_keys_take_yaml_maps_as_flags():
    import argparse

    from cli.config_flags import add_config_flags, config_overrides

    p = argparse.ArgumentParser()
    add_config_flags(p)
    args = p.parse_args(
        [
            "--early-stop",
            "{rule: no_improvement, patience: 3}",
            "--beta-schedule",
            "{kind: linear, end: 0.1, horizon: 50}",
        ]
    )
    cfg = make_config({**BASE, **config_overrides(args)})
    assert cfg.early_stop is not None and cfg.early_stop.patience == 3
    assert cfg.beta_schedule is not None and cfg.beta_schedule.horizon == 50


def test_macb_up_out_copies_the_learners_best_point_beside_the_last(tmp_path):
    """`macb up --run CONFIG --out DIR` (`write_results` with the cluster's data dir)
    copies a run's best.pt from the learner's folder beside its checkpoint.pt; a run
    without one gets none."""
    from cli.api import write_results

    class Api:  # the few calls write_results makes, for runs with no points
        def metrics_csv(self, run: str) -> str:
            return "episode\n"

        def all_points(self, run: str) -> list:
            return []

        def experiment_csv(self, exp: str) -> str:
            return "run,episode\n"

    data = tmp_path / "data"
    for run, names in (("r1", ("checkpoint.pt", "best.pt")), ("r2", ("checkpoint.pt",))):
        (data / "learner" / run).mkdir(parents=True)
        for name in names:
            (data / "learner" / run / name).write_bytes(f"{run} {name}".encode())
    runs = [{"id": r, "config": {}, "live": {}} for r in ("r1", "r2")]
    write_results(Api(), {"id": "e", "runs": runs}, tmp_path / "out", plot=False, data_dir=data)
    out = tmp_path / "out"
    assert (out / "r1" / "best.pt").read_bytes() == b"r1 best.pt"
    assert (out / "r1" / "checkpoint.pt").read_bytes() == b"r1 checkpoint.pt"
    assert not (out / "r2" / "best.pt").exists() and (out / "r2" / "checkpoint.pt").exists()
