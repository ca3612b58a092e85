"""The one-process trainer end to end on the real mpe2 tasks (short runs)."""

import csv
import json

import numpy as np
import pytest
import torch

from cli.trainer import METRIC_FIELDS, load_checkpoint, train
from shared.config import make_config
from shared.envs.tasks import make_task
from shared.run.factories import build_exploration
from shared.run.rollout import Collector, evaluate

SMALL = {"hidden": (32, 32), "batch_size": 16, "eval_episodes": 3}


def cfg(**kw):
    return make_config({**SMALL, **kw})


def test_outputs_metrics_config_and_checkpoint(tmp_path):
    c = cfg(
        task="speaker_listener",
        algo="cen-maddpg",
        explore="cen-macb",
        episodes=8,
        eval_every=4,
        k=64,
    )
    rows = train(c, tmp_path, progress=False)
    assert [r["episode"] for r in rows] == [4, 8]
    with open(tmp_path / "metrics.csv") as f:
        csv_rows = list(csv.DictReader(f))
    jsonl = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert len(csv_rows) == len(jsonl) == 2
    assert set(METRIC_FIELDS) <= set(csv_rows[0]) and set(METRIC_FIELDS) <= set(jsonl[0])
    assert json.loads((tmp_path / "config.json").read_text())["k"] == 64
    ck = load_checkpoint(tmp_path / "checkpoint.pt")  # weights_only=True inside
    assert ck["counters"] == {"env_steps": 160, "episodes": 8, "updates": 60}
    assert int(ck["tables"]["table0"]["counts"].sum()) == 160
    assert isinstance(ck["learner"]["actors"][0]["net.0.weight"], torch.Tensor)


@pytest.mark.parametrize(
    "task, algo, explore",
    [
        ("simple", "ddpg", "dis-macb"),
        ("spread", "dis-maddpg", "dis-macb"),
        ("spread", "cen-maddpg", "cen-macb"),
        ("speaker_listener", "cen-maddpg", "dis-macb"),
    ],
)
def test_counts_equal_collected_training_transitions_exactly(task, algo, explore):
    """Counting happens once per collected step: evaluation and sampling add nothing."""
    c = cfg(task=task, algo=algo, explore=explore, episodes=6, eval_every=1, k=32)
    rows = train(c, None, progress=False)
    for r in rows:
        assert r["counted_transitions"] == r["env_steps"] == r["episode"] * 20
        assert r["updates"] == max(0, r["env_steps"] - 100)
        assert 0 < r["table_size"] <= r["env_steps"]


def test_evaluation_changes_no_count_and_uses_no_noise():
    env = make_task("speaker_listener")
    c = cfg(explore="cen-macb", k=16)
    ex = build_exploration(c, env.spec)
    col = Collector(env, 0.1, seed=0)
    for _ in range(40):
        tr = col.step(lambda o: np.zeros((len(o), 5), np.float32))
        ex.observe(tr.obs[None], tr.act[None])
    before = ex.tables[0].to_arrays()[1].copy()
    envs = [make_task("speaker_listener", seed=s) for s in range(3)]
    calls = []

    def policy(o):
        calls.append(o.shape[0])
        return np.full((len(o), 5), 0.5, np.float32)

    res = evaluate(policy, envs, 7)
    assert np.array_equal(before, ex.tables[0].to_arrays()[1]) and ex.tables[0].total == 40
    assert res.episodes == 7 and res.steps == 7 * 20
    assert calls[:20] == [3] * 20, "evaluation runs its envs in lockstep, batched"
    assert 0.0 <= res.success_rate <= 1.0


@pytest.mark.parametrize("lanes", [1, 2])
def test_same_seed_same_metrics_different_seed_different(lanes):
    """Bit-identical reruns with a fixed number of lanes (auto may switch between 1 and 2,
    which changes results at the level of floating-point rounding)."""
    c = cfg(
        task="spread",
        algo="cen-maddpg",
        explore="cen-macb",
        episodes=8,
        eval_every=4,
        learner_lanes=lanes,
    )
    strip = ("steps_per_sec", "train_steps_per_sec", "wall_s")
    a = [{k: v for k, v in r.items() if k not in strip} for r in train(c, None, progress=False)]
    b = [{k: v for k, v in r.items() if k not in strip} for r in train(c, None, progress=False)]
    d = c.model_copy(update={"seed": 1})
    e = [{k: v for k, v in r.items() if k not in strip} for r in train(d, None, progress=False)]
    assert a == b
    assert a != e


def test_time_limit_terminal_option_marks_last_step_done():
    env = make_task("simple")
    for terminal in (False, True):
        col = Collector(env, 0.1, seed=0, time_limit_terminal=terminal)
        dones = [col.step(lambda o: np.zeros((1, 2), np.float32)).done for _ in range(40)]
        expected = [0.0] * 40 if not terminal else ([0.0] * 19 + [1.0]) * 2
        assert dones == expected


def test_numpy_blas_runs_on_one_thread_while_training_and_is_restored():
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas_threads() -> list[int]:
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    seen: list[list[int]] = []
    c = cfg(task="simple", algo="ddpg", explore="dis-macb", episodes=4, eval_every=2, k=512)
    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        train(c, None, progress=False, on_metrics=lambda row: seen.append(blas_threads()))
        after = blas_threads()
    assert before and all(n == 2 for n in before)  # numpy's BLAS is visible and at 2
    assert len(seen) == 2 and all(n == 1 for threads in seen for n in threads)
    assert after == before


def test_rows_say_what_the_bonus_did_and_the_log_names_a_constant_shift(caplog):
    """k=512 on speaker_listener: every key is new, so Cen-MACB's bonus is exactly beta
    (a constant shift, what the constant arm does by design); with k=4 keys repeat and
    the bonus varies."""
    base = dict(task="speaker_listener", algo="cen-maddpg", episodes=15, eval_every=5)
    with caplog.at_level("WARNING", logger="macb.trainer"):
        rows = train(cfg(**base, explore="cen-macb", k=512, beta=0.8), None, progress=False)
    # Nothing is sampled before learning_starts (100 steps = 5 episodes): all zero.
    assert rows[0]["bonus_mean"] == rows[0]["sampled_count1_pct"] == 0.0
    wide = rows[1:]
    assert [r["sampled_count1_pct"] for r in wide] == [100.0, 100.0]
    assert all(r["bonus_std"] == 0.0 for r in wide)
    assert wide[-1]["bonus_mean"] == pytest.approx(0.8)
    assert "the bonus is a constant shift" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="macb.trainer"):
        narrow = train(cfg(**base, explore="cen-macb", k=4, beta=0.8), None, progress=False)[1:]
    assert all(r["bonus_std"] > 0 for r in narrow)
    assert all(r["sampled_count1_pct"] < 100 for r in narrow)
    assert all(0 < r["bonus_mean"] < 0.8 for r in narrow)
    assert "constant shift" not in caplog.text
    const = train(cfg(**base, explore="constant", beta=0.3), None, progress=False)[1:]
    assert all(r["bonus_std"] == 0 and r["bonus_mean"] == pytest.approx(0.3) for r in const)
    assert all(r["sampled_count1_pct"] == 0.0 for r in const)  # no tables
    none = train(cfg(**base, explore="none"), None, progress=False)[1:]
    assert all(r["bonus_mean"] == 0 and r["bonus_std"] == 0 for r in none)


@pytest.mark.parametrize(
    "task, algo", [("speaker_listener", "cen-maddpg"), ("spread", "dis-maddpg")]
)
def test_per_agent_minibatches_train_exactly(task, algo):
    """`minibatch: per-agent` draws one minibatch per agent per update (the thesis code):
    a run completes with every transition counted once and one update per step after the
    warm-up."""
    base = dict(task=task, algo=algo, explore="cen-macb", k=64, episodes=8, eval_every=4)
    rows = train(cfg(**base, minibatch="per-agent"), None, progress=False)
    assert rows[-1]["counted_transitions"] == rows[-1]["env_steps"] == 160
    assert rows[-1]["updates"] == 160 - 100
    assert 0 < rows[-1]["bonus_mean"] <= 0.8


def test_per_agent_and_shared_runs_end_with_different_weights(tmp_path):
    base = dict(task="speaker_listener", algo="cen-maddpg", k=64, episodes=8, eval_every=8)
    train(cfg(**base), tmp_path / "shared", progress=False)
    train(cfg(**base, minibatch="per-agent"), tmp_path / "per", progress=False)
    a = load_checkpoint(tmp_path / "shared" / "checkpoint.pt")["learner"]["critics"][0]
    b = load_checkpoint(tmp_path / "per" / "checkpoint.pt")["learner"]["critics"][0]
    assert not torch.equal(a["net.0.weight"], b["net.0.weight"])


@pytest.mark.parametrize(
    ("task", "algo", "explore", "obs_dims"),
    [
        ("simple", "ddpg", "dis-macb", (4,)),
        ("spread", "cen-maddpg", "cen-macb", (10, 10)),  # comm-free (row T3)
        ("speaker_listener", "cen-maddpg", "cen-macb", (11, 11)),  # padded speaker (T4)
    ],
)
def test_macb_train_profile_thesis_runs_each_task(tmp_path, task, algo, explore, obs_dims):
    """`macb train --profile thesis`: the thesis code's task options reach the env, the
    networks and the count tables, and counting stays exact."""
    from cli.main import main

    out = tmp_path / "run"
    argv = ["train", "--profile", "thesis", "--task", task, "--algo", algo]
    argv += ["--explore", explore, "--episodes", "7", "--eval-every", "7", "--k", "32"]
    argv += ["--hidden", "16,16", "--batch-size", "8", "--eval-episodes", "2"]
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    written = json.loads((out / "config.json").read_text())
    assert written["profile"] == "thesis" and written["success_terminal"] is True
    assert written["pad_obs"] is True and written["comm_obs"] is False
    assert written["integrator"] == "velocity-first" and written["warmup"] == "random"
    assert written["landmark_size"] == (0.075 if task == "speaker_listener" else None)
    ck = load_checkpoint(out / "checkpoint.pt")
    assert ck["counters"] == {"env_steps": 140, "episodes": 7, "updates": 40}
    widths = [a["net.0.weight"].shape[1] for a in ck["learner"]["actors"]]
    assert tuple(widths) == obs_dims
    tables = [t for name, t in sorted(ck["tables"].items())]
    assert [int(t["counts"].sum()) for t in tables] == [140] * len(tables)
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["env_steps"] == rows[-1]["counted_transitions"] == 140


def test_bf16_run_trains_reruns_exactly_and_checkpoints_fp32(tmp_path, monkeypatch):
    """`precision: bf16` in `macb train`: a run completes as an fp32 run does, reruns of
    one seed are equal (fixed lanes), its weights differ from the fp32 run's, and its
    checkpoint holds fp32 weights the reference learner loads."""
    from shared.core.learners import MADDPG, AgentDims, LearnerSpec, precision

    monkeypatch.setattr(precision, "native_bf16", lambda: True)  # bf16 on any CPU
    base = dict(task="speaker_listener", algo="cen-maddpg", k=64, episodes=8, eval_every=4)
    base.update(learner_lanes=1)
    rows = train(cfg(**base, precision="bf16"), tmp_path / "bf16", progress=False)
    again = train(cfg(**base, precision="bf16"), None, progress=False)
    train(cfg(**base), tmp_path / "fp32", progress=False)
    drop = ("steps_per_sec", "train_steps_per_sec", "wall_s")
    assert [{k: v for k, v in r.items() if k not in drop} for r in rows] == [
        {k: v for k, v in r.items() if k not in drop} for r in again
    ]
    assert rows[-1]["updates"] == 60 and np.isfinite(rows[-1]["eval_return"])
    low = load_checkpoint(tmp_path / "bf16" / "checkpoint.pt")["learner"]
    full = load_checkpoint(tmp_path / "fp32" / "checkpoint.pt")["learner"]
    w = low["critics"][0]["net.0.weight"]
    assert w.dtype == torch.float32 and not torch.equal(w, full["critics"][0]["net.0.weight"])
    agents = [AgentDims(3, (0.0,) * 3, (1.0,) * 3), AgentDims(11, (-1.0, -1.0), (1.0, 1.0))]
    MADDPG(agents, LearnerSpec(hidden=SMALL["hidden"])).load_state_dict(low)
