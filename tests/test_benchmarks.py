"""The benchmarks still run: a smoke run of bench_rollout (timings are not asserted)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

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
