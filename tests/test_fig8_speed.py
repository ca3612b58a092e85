"""What bench_fig8.py measures the figure with, and the loop changes it measured: a
training process's heap setting leaves every row as it was, a slow cut spaces the next
ones out, and MACB_GROUP_TIMING writes each group's split at every point."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cli.trainer import (
    CUT_MAX_WAIT_S,
    CUT_SPACING,
    CUT_SPACING_OVER,
    TIMING_KEYS,
    GroupRun,
    train_group,
)
from shared.config import make_config

ROOT = Path(__file__).resolve().parents[1]
TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")
SMALL = {
    "task": "speaker_listener",
    "algo": "cen-maddpg",
    "profile": "thesis",
    "explore": "cen-macb",
    "k": 16,
    "hidden": [32, 32],
    "episodes": 6,
    "eval_episodes": 4,
    "learning_starts": 40,
    "batch_size": 16,
}


def rows_of(folder: Path) -> list[dict]:
    rows = [json.loads(x) for x in (folder / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def test_the_steady_heap_changes_no_row(tmp_path: Path) -> None:
    """`macb train --seeds` (one group of two runs) with glibc's malloc thresholds and with
    the steady heap: each process sets its heap once, so each way runs in its own. The
    thesis's 400-300 networks: their gradients are blocks glibc first maps afresh."""
    config = tmp_path / "c.json"
    config.write_text(json.dumps({**SMALL, "hidden": [400, 300]}))
    outs = {}
    for heap in ("0", "1"):
        out = tmp_path / f"heap{heap}"
        env = {**os.environ, "MACB_STEADY_HEAP": heap}
        argv = [sys.executable, "-m", "cli", "train", "--config", str(config), "--seeds", "0", "1"]
        argv += ["--out", str(out), "--quiet"]
        proc = subprocess.run(argv, env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        outs[heap] = out
    for run in ("seed-0", "seed-1"):
        base, steady = rows_of(outs["0"] / run), rows_of(outs["1"] / run)
        assert len(base) == 6 and steady == base


def test_a_slow_cut_spaces_the_next_ones_out(tmp_path: Path) -> None:
    g = GroupRun([make_config(SMALL)], [tmp_path / "r"], cut_every_s=60.0)
    g.last_cut = time.monotonic() - 70
    assert g.cut_due()  # no cut yet: the interval alone
    g.cut_log = [(1, 2.0, 0, 0)]  # a cut of 2 s: the next waits 50 x 2 s
    assert 2.0 * CUT_SPACING > 70 and not g.cut_due()
    g.cut_log = [(1, 0.5, 0, 0)]
    assert g.cut_due()
    # one cut slowed by a load beside the run (60 s) among fast ones spaces nothing out:
    # the least of the last CUT_SPACING_OVER counts
    g.cut_log = [(1, 0.5, 0, 0), (2, 0.5, 0, 0), (3, 60.0, 0, 0)]
    assert CUT_SPACING_OVER == 3 and g.cut_due()
    g.cut_log = [(1, 0.5, 0, 0), (2, 2.0, 0, 0), (3, 60.0, 0, 0), (4, 60.0, 0, 0)]
    assert not g.cut_due()  # the last three all took 2 s or more
    # however slow the cuts, they are at most CUT_MAX_WAIT_S apart ...
    g.cut_log = [(1, 1e3, 0, 0)]
    g.last_cut = time.monotonic() - CUT_MAX_WAIT_S + 5
    assert not g.cut_due()
    g.last_cut = time.monotonic() - CUT_MAX_WAIT_S - 1
    assert g.cut_due()
    g.cut_every_s = 2 * CUT_MAX_WAIT_S  # ... unless --cut-every asks for fewer
    assert not g.cut_due()
    g.cut_every_s = 0.0  # every point, however slow
    g.cut_log = [(1, 1e6, 0, 0)]
    assert g.cut_due()


def test_group_timing_writes_every_points_split(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("MACB_GROUP_TIMING", str(tmp_path / "timing"))
    cfgs = [make_config({**SMALL, "seed": s}) for s in (0, 1)]
    train_group(cfgs, [tmp_path / "a", tmp_path / "b"], progress=False)
    data = json.loads((tmp_path / "timing" / "timing-a.json").read_text())
    assert data["runs"] == ["a", "b"] and data["torch_threads"] == 1
    assert all(n == 1 for api, n in data["blas"])
    points = data["points"]
    assert [p["episode"] for p in points] == [1, 2, 3, 4, 5, 6]
    for key in TIMING_KEYS:
        assert points[-1][key] >= points[0][key] >= 0
    assert points[-1]["update"] > 0 and points[0]["update"] == 0  # updates from step 41
    assert points[-1]["cut"] > 0  # the first point's cut, before the last snapshot
    parts = sum(points[-1][k] for k in TIMING_KEYS)
    assert parts <= points[-1]["wall"]


@pytest.mark.slow
def test_bench_fig8_reports_the_figure_against_its_floor(tmp_path: Path) -> None:
    out = tmp_path / "fig8.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_fig8.py"), "--quick"]
    argv += ["--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=900, check=False)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    (rnd,) = result["rounds"]
    groups = rnd["figure"]["groups"]
    assert len(groups) == 2 and sorted(len(g["runs"]) for g in groups) == [6, 6]
    for g in groups:
        assert g["parts_ms"]["update"] > 0 and g["step_ms"] > g["parts_ms"]["update"]
        assert g["torch_threads"] == 1
    assert rnd["floor"]["ms"] > 0 and rnd["update"]["ms"] > 0
    assert {"figure / floor", "update / floor"} <= set(result["summary"]["ratios"])
    assert "| part of a training step | ms | share |" in proc.stdout
    assert "CPU: " in proc.stdout
