"""`macb up`: the whole local cluster as processes, a run on it, and a clean shutdown."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

from shared import provenance
from shared.learners.precision import native_bf16
from tests.conftest import ROOT, free_port, wait_for

TINY = """\
task: speaker_listener
algo: cen-maddpg
explore: cen-macb
k: 64
episodes: 12
eval_every: 4
eval_episodes: 2
hidden: [32, 32]
batch_size: 16
"""


def processes_with(marker: str) -> list[str]:
    out = subprocess.run(["pgrep", "-af", marker], capture_output=True, text=True).stdout
    return [line for line in out.splitlines() if "pgrep" not in line]


def up(tmp_path, *extra: str) -> tuple[subprocess.Popen, str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cli",
            "up",
            "--endpoint",
            endpoint,
            "--data-dir",
            str(tmp_path / "data"),
            "--api-port",
            str(free_port()),
            "--quiet",
            *extra,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    return proc, endpoint


def test_up_runs_an_experiment_and_leaves_nothing_running(tmp_path):
    """Asked for bf16, which runs where the CPU has it: out/provenance.json, as the
    learner reported it, says which precision ran."""
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY + "precision: bf16\n")
    proc, endpoint = up(tmp_path, "--run", str(cfg), "--out", str(tmp_path / "out"))
    out, _ = proc.communicate(timeout=240)
    assert proc.returncode == 0, out
    assert "completed" in out and "cluster stopped" in out
    with open(tmp_path / "out" / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["episode"]) for r in rows] == [4, 8, 12]
    assert int(rows[-1]["counted_transitions"]) == 12 * 20
    assert float(rows[-1]["replay_ratio"]) == 1.0
    assert (tmp_path / "out" / "plot.png").stat().st_size > 10_000
    assert (tmp_path / "out" / "checkpoint.pt").stat().st_size > 1000
    (start,) = json.loads((tmp_path / "out" / "provenance.json").read_text())["starts"]
    assert start["role"] == "learner" and start["code"] == provenance.code()
    ran = "bf16" if native_bf16() else "fp32"
    assert start["learner"]["precision_asked"] == "bf16" and start["learner"]["precision"] == ran
    assert "dashboard" in out and (tmp_path / "data" / "api.sqlite3").exists()
    for name in ("router", "counter", "learner", "evaluator", "actor0", "api"):
        assert (tmp_path / "data" / "logs" / f"{name}.log").exists()
    assert cluster_processes(endpoint, tmp_path) == []


def test_slots_run_two_runs_at_once_each_exact(tmp_path):
    """`macb up --slots 2`: two learners and evaluators, two actors, one counter; an
    experiment of two seeds has both runs running at once, and each is exact."""
    import sqlite3

    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY.replace("episodes: 12", "episodes: 40"))
    proc, endpoint = up(
        tmp_path,
        "--slots",
        "2",
        "--run",
        str(cfg),
        "--seeds",
        "0",
        "1",
        "--out",
        str(tmp_path / "out"),
    )
    out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 0, out
    with sqlite3.connect(tmp_path / "data" / "api.sqlite3") as db:
        runs = db.execute("SELECT id, status, started, ended, assign FROM runs").fetchall()
    assert [r[1] for r in runs] == ["completed", "completed"], runs
    (a, b) = runs
    assert a[2] < b[3] and b[2] < a[3], f"the two runs did not overlap: {runs}"
    learners = {json.loads(r[4])["learner"] for r in runs}
    assert learners == {"learner", "learner1"}, learners
    for run_id, *_ in runs:
        with open(tmp_path / "out" / run_id / "metrics.csv") as f:
            rows = list(csv.DictReader(f))
        assert [int(r["episode"]) for r in rows] == [4 * i for i in range(1, 11)]
        assert int(rows[-1]["counted_transitions"]) == 40 * 20
        assert float(rows[-1]["replay_ratio"]) == 1.0
    assert cluster_processes(endpoint, tmp_path) == []


def test_sigterm_stops_every_service_and_the_router(tmp_path):
    proc, endpoint = up(tmp_path)
    from shared.control import discover

    with _client(endpoint) as bus:
        wait_for(lambda: len(discover(bus)) >= 4, timeout=90, what="services up")
    children = cluster_processes(endpoint, tmp_path)
    assert len(children) >= 5, f"router and four services run as processes: {children}"
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert "cluster stopped" in out
    deadline = time.monotonic() + 5
    while cluster_processes(endpoint, tmp_path) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert cluster_processes(endpoint, tmp_path) == [], "no orphan process"


def cluster_processes(endpoint: str, tmp_path) -> list[str]:
    """`macb serve` processes of this test's cluster (router by port, services by data dir)."""
    lines = processes_with(endpoint.split(":")[-1]) + processes_with(str(tmp_path / "data"))
    return sorted({line for line in lines if " serve " in line})


def _client(endpoint):
    from tests.conftest import wait_port

    wait_port(endpoint, timeout=30)
    from shared.bus import Bus

    return Bus([endpoint])
