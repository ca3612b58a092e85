"""The benchmarks still run: a smoke run of bench_rollout (timings are not asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from shared.core.learners.precision import native_bf16

ROOT = Path(__file__).resolve().parents[1]


def test_bench_rollout_runs_and_writes_its_table(tmp_path: Path) -> None:
    out = tmp_path / "rollout.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_rollout.py"), "--quick"]
    argv += ["--tasks", "simple", "--rounds", "1", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert "| simple | eval_point |" in proc.stdout
    rows = json.loads(out.read_text())["rows"]
    assert [r["measure"] for r in rows] == ["eval_point", "actor_episode"]
    for row in rows:
        for way in ("platform", "per_agent", "baseline"):
            assert row[f"{way}_ms"] > 0


def test_bench_rollout_refuses_an_unknown_task(tmp_path: Path) -> None:
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_rollout.py"), "--tasks", "nope"]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2 and "unknown task(s) ['nope']" in proc.stderr


def test_bench_cuts_runs_and_reports_bytes_and_time_per_cut(tmp_path: Path) -> None:
    out = tmp_path / "cuts.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_cuts.py"), "--quick"]
    argv += ["--episodes", "20", "--eval-every", "5", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(out.read_text())["summary"]
    assert summary["cuts_per_often_run"] == 4  # one per evaluation point
    assert summary["replay_bytes_per_cut"] > 0 and summary["cut_file_bytes"] > 0
    assert 0 < summary["share_at_default_interval"] < 1


def test_bench_learner_bf16_table_runs(tmp_path: Path) -> None:
    """bench_learner's bf16 table, one quick round (skipped inside on a CPU without
    native bf16, which it says)."""
    out = tmp_path / "learner.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_learner.py"), "--quick"]
    argv += ["--precision", "bf16", "--repeats", "1", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert "rows" not in result  # the fp32 table was not asked for
    if not result["native_bf16"]:
        assert "bf16: skipped" in proc.stdout
        return
    assert "| speaker_listener | cen-maddpg | 2 | 1 |" in proc.stdout
    sl = [r for r in result["bf16_rows"] if r["task"] == "speaker_listener"]
    assert [r["threads"] for r in sl] == [1, 2]
    for row in sl:
        for way in ("batched", "bf16", "floor", "floor_bf16"):
            assert row[f"{way}_updates_per_s"] > 0


@pytest.mark.slow
def test_bench_forkserver_times_both_ways_of_starting_the_cluster(tmp_path: Path) -> None:
    out = tmp_path / "forkserver.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_forkserver.py"), "--quick"]
    proc = subprocess.run([*argv, "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    assert [len(result["rounds"][v]) for v in ("exec", "fork")] == [1, 1]
    for row in result["median"].values():
        assert row["exec"] > 0 and row["fork"] > 0 and row["ratio_fork_exec"] > 0
    assert "fork/exec" in proc.stdout and result["cpu"]


def test_bench_resume_kills_the_learner_and_times_its_resume(tmp_path: Path) -> None:
    out = tmp_path / "resume.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_resume.py"), "--quick"]
    proc = subprocess.run(
        [*argv, "--out", str(out)], capture_output=True, text=True, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stderr
    (round_,) = json.loads(out.read_text())["rounds"]
    assert round_["counted"] == 60 * 20 and round_["replay_ratio"] == 1.0
    assert 0 < round_["restart_after_kill_s"] < round_["first_update_after_restart_s"] + 1
    assert round_["cut_bytes"] > 0 and round_["cut_ms_mean_after_resume"] > 0


def test_bench_parity_refuses_an_unknown_case(tmp_path: Path) -> None:
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_parity.py"), "--cases", "nope"]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2 and "unknown case(s) ['nope']" in proc.stderr


@pytest.mark.slow
def test_bench_cluster_bf16_runs_both_precisions_and_reports_ratios(tmp_path: Path) -> None:
    """One short round of this tree's cluster in fp32 and bf16 (the baseline worktree is
    left out: a shallow clone may lack its commit); rates come from real metric rows."""
    out = tmp_path / "cluster.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_cluster_bf16.py")]
    argv += ["--variants", "fp32,bf16", "--rounds", "1", "--episodes", "12", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert [r["variant"] for r in result["runs"]] == ["fp32", "bf16"]
    for run in result["runs"]:
        assert run["steady"] > 0 and run["overall"] > 0 and run["rows"] == 12
    assert set(result["ratios"]) == {"bf16/fp32 steady", "bf16/fp32 overall"}
    # What each run ran in, from its provenance.json: bf16 only where the CPU has it.
    assert [r["ran"] for r in result["runs"]] == ["fp32", "bf16" if native_bf16() else "fp32"]
    assert ("bf16 ran fp32" in proc.stdout) == (not native_bf16())


def test_bench_cluster_bf16_variants_set_precision_and_lanes(tmp_path: Path) -> None:
    """What each variant's config says: `-1t` pins the update to one thread, `base`
    sets neither key (968ebf2's schema has no `precision`)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from bench_cluster_bf16 import VARIANTS, variant_keys, write_config
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    assert variant_keys("base") == (None, None)
    assert variant_keys("fp32") == ("fp32", None)
    assert variant_keys("bf16-unfused") == ("bf16", None)
    assert variant_keys("fp32-1t") == ("fp32", "1")
    assert variant_keys("bf16-1t") == ("bf16", "1")
    assert set(VARIANTS) == {"base", "fp32", "bf16", "bf16-unfused", "fp32-1t", "bf16-1t"}
    with pytest.raises(ValueError, match="unknown variant 'bf17'"):
        variant_keys("bf17")
    cfg = tmp_path / "c.yaml"
    write_config(cfg, 12, *variant_keys("bf16-1t"))
    lines = cfg.read_text().splitlines()
    assert "precision: bf16" in lines and "learner_lanes: 1" in lines
    write_config(cfg, 12, *variant_keys("base"))
    assert not any(
        line.startswith(("precision", "learner_lanes")) for line in cfg.read_text().splitlines()
    )


@pytest.mark.slow
def test_stack_probe_two_cores_prints_the_precisions_this_cpu_runs() -> None:
    """fp32 and bf16 rows where the CPU has native bf16; elsewhere fp32 only, and it
    says bf16 was skipped (a bf16 learner there runs fp32: its row would be mislabelled)."""
    argv = [sys.executable, str(ROOT / "benchmarks" / "stack_probe.py"), "--two-cores"]
    argv += ["--runs", "2", "--rounds", "1", "--seconds", "0.3"]
    proc = subprocess.run(
        argv, capture_output=True, text=True, timeout=300, check=False, cwd=ROOT / "benchmarks"
    )
    assert proc.returncode == 0, proc.stderr
    rows = {
        line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
        for line in proc.stdout.splitlines()
        if line.startswith(("| fp32 ", "| bf16 "))
    }
    assert set(rows) == ({"fp32", "bf16"} if native_bf16() else {"fp32"})
    assert ("bf16: skipped" in proc.stdout) == (not native_bf16())
    for cells in rows.values():
        assert len(cells) == 5
        rates = [float(cells[i]) for i in (0, 1, 3)]  # run-updates/s of the three cases
        ratios = [float(cells[i].rstrip("x")) for i in (2, 4)]
        assert all(r > 0 for r in rates + ratios)


@pytest.mark.slow
def test_bench_slots_runs_one_two_and_three_at_once(tmp_path: Path) -> None:
    """One short round of one run alone, two and three at once, through `macb up
    --slots`; every run's rate comes from its own metric rows, and each count has its
    ratio to the same round's run alone."""
    out = tmp_path / "slots.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_slots.py"), "--rounds", "1"]
    argv += ["--episodes", "12", "--precision", "fp32", "--slots", "3", "2", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=900, check=False)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert result["slots"] == [2, 3]
    assert [(r["slots"], len(r["per_run"])) for r in result["runs"]] == [(1, 1), (2, 2), (3, 3)]
    for run in result["runs"]:
        assert all(x > 0 for x in run["per_run"]) and run["total"] == sum(run["per_run"])
        assert run["ran"] == ["fp32"] * run["slots"]  # each run's provenance.json
    alone = result["runs"][0]["total"]
    for slots, run in zip(("2", "3"), result["runs"][1:]):
        summary = result["summary"][slots]
        assert summary["ratio"] == pytest.approx(run["total"] / alone)
        assert summary["fig8_pair_hours"] == pytest.approx(
            2 * 3 * 40_000 * 20 / run["total"] / 3600
        )
    assert "| 3 runs at once |" in proc.stdout and "figure 8's headline pair" in proc.stdout


def test_lockstep_probe_times_both_designs_and_names_the_cpu() -> None:
    argv = [sys.executable, str(ROOT / "benchmarks" / "lockstep_probe.py")]
    argv += ["--rounds", "1", "--calls", "2"]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("CPU: ")
    rows = {
        line.split("|")[1].strip(): line.split("|")[3].strip()
        for line in proc.stdout.splitlines()
        if line.startswith(("| central", "| weights"))
    }
    # One observation and one action against every actor weight: sizes follow the shapes.
    assert int(rows["central inference"].replace(",", "")) < 1_000
    assert int(rows["weights every step"].replace(",", "")) > 500_000
    assert "weights every step / central inference:" in proc.stdout


def test_bench_sketch_measures_both_stores_and_the_sketch_stays_its_size(tmp_path: Path) -> None:
    out = tmp_path / "sketch.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_sketch.py"), "--keys", "2000"]
    argv += ["20000", "--random-from", "20000", "--steps", "300", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    memory = {(r["store"], r["keys"]): r for r in result["memory"]}
    assert (
        memory["exact", 20000]["source"] == "random" and memory["exact", 2000]["distinct"] == 2000
    )
    assert memory["exact", 20000]["memory_bytes"] > 5 * memory["exact", 2000]["memory_bytes"]
    assert memory["sketch", 20000]["memory_bytes"] == memory["sketch", 2000]["memory_bytes"]
    assert all(e["under_true"] == 0 for e in result["real_stream"])
    assert "| 20,000 | random | sketch |" in proc.stdout


def test_gpu_probe_runs_on_the_cpu_and_skips_without_a_gpu(tmp_path: Path) -> None:
    """benchmarks/gpu_probe.py, ready for a GPU window: a quick run on the CPU writes its
    row; asked for CUDA where there is none it says it skipped and writes that. Its
    hard-coded agents are figure 8's speaker_listener in profile thesis."""
    import importlib.util

    from shared.config import make_config
    from shared.envs.tasks import task_spec_for

    out = tmp_path / "probe.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "gpu_probe.py"), "--out", str(out)]
    proc = subprocess.run([*argv, "--device", "cpu", "--quick"], capture_output=True,
                          text=True, timeout=300, check=False)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    (row,) = json.loads(out.read_text())["rows"]
    assert row["runs"] == 2 and row["update_ms"] > 0 and row["act_ms"] > 0
    assert row["ops_per_update"] > 0 and row["syncs_per_update"] is None
    if not torch.cuda.is_available():
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
        assert proc.returncode == 0 and "gpu_probe: skipped: no CUDA device" in proc.stdout
        assert "skipped" in json.loads(out.read_text())
    spec = importlib.util.spec_from_file_location("gpu_probe", ROOT / "benchmarks/gpu_probe.py")
    assert spec is not None and spec.loader is not None
    probe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(probe)
    cfg = make_config({"task": "speaker_listener", "algo": "cen-maddpg", "profile": "thesis"})
    task = task_spec_for(cfg)
    assert [(a.obs_dim, a.act_low, a.act_high) for a in task.agents] == [
        (a.obs_dim, a.act_low, a.act_high) for a in probe.AGENTS
    ]
    assert (cfg.batch_size, cfg.hidden, cfg.minibatch) == (probe.BATCH, (400, 300), "per-agent")


def test_bench_group_price_checks_both_ways_agree_and_names_the_cpu(tmp_path: Path) -> None:
    """bench_group.py price, quick: fig8's sparse pair in profile thesis (6 runs, one
    minibatch per agent), the group's way and the per-run way giving the same arrays
    (checked inside before timing), both timed in the same rounds."""
    out = tmp_path / "price.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_group.py"), "price", "--quick"]
    argv += ["--fill", "300", "--rounds", "2", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert (row["runs"], row["profile"], row["minibatches"], row["batch"]) == (6, "thesis", 2, 100)
    assert row["same_arrays"] is True and row["fill"] == 300
    assert row["group_ms"] > 0 and row["per_run_ms"] > 0 and row["per_run_over_group"] > 0
    assert result["cpu"] and f"CPU: {result['cpu']}" in proc.stdout
    assert "| 6 | thesis | 2 x 100 | 300 |" in proc.stdout


def test_bus_order_probe_counts_pairs_and_one_subscription_keeps_its_order() -> None:
    """The probe behind docs/architecture.md's "Order on the bus": four cases, each
    counted out of the pairs sent; one subscription's messages come in order (what the
    services rely on), whatever several subscriptions do."""
    argv = [sys.executable, str(ROOT / "benchmarks" / "bus_order_probe.py"), "--pairs", "300"]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("CPU: ") and "zenoh " in proc.stdout
    counts = {
        line[:61].strip(): int(line.split(" of ")[0].split()[-1])
        for line in proc.stdout.splitlines()[1:]
    }
    assert len(counts) == 4 and all(0 <= n <= 300 for n in counts.values()), proc.stdout
    assert [n for case, n in counts.items() if case.startswith("one subscriber")] == [0, 0]


def test_the_fig8_projections_count_the_shipped_configs_steps() -> None:
    """bench_group's and bench_slots' hours for figure 8's headline pair are its six
    runs' env steps as configs/fig8 ships them (episodes x episode_len), not a length
    the figure once had."""
    from shared.config import TrainConfig, read_config_file

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from _harness import FIG8_PAIR_RUN_STEPS
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    steps = 0
    for arm in ("sparse", "sparse-cen-macb"):
        raw = read_config_file(ROOT / "configs" / "fig8" / f"{arm}.yaml")
        seeds = raw.pop("seeds")
        cfg = TrainConfig.model_validate(raw)
        steps += len(seeds) * cfg.episodes * cfg.episode_len
    assert steps == FIG8_PAIR_RUN_STEPS
