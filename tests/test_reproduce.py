"""`macb reproduce` end to end: it starts its own cluster (no API answers on its port),
runs three of figure 3's arms (a count arm, beta 0.0 and a control) x two seeds, is
interrupted, resumes where it stopped, writes the figure and the report, and a third
time re-runs nothing. Every arm of every figure is built and reported by
tests/test_figures.py and tests/test_local.py; this is the cluster's resume.

Real processes, HTTP and SQLite: the command is a child process with free ports and a
temporary data dir; the store file is read with `Store` between the commands.
"""

from __future__ import annotations

import json
import signal
import time

import httpx
import pytest
from PIL import Image

from cli.reproduce.figures import FIGURES
from cli.results import read_points
from services.api.store import Store
from tests.harness import cluster_processes, free_port, macb, spawn, wait_for

EPISODES = 60  # x 3 arms x 2 seeds, one run at a time: several seconds each, so a
# SIGINT after the second run finds the third running
ARMS = ("beta=0.0", "beta=0.8", "constant beta=0.8 (control)")  # fig3's order


def _completed(url: str) -> int:
    try:
        exps = httpx.get(f"{url}/experiments", timeout=5).json()["experiments"]
    except (httpx.HTTPError, ValueError, KeyError):
        return 0
    return sum(r["status"] == "completed" for e in exps for r in e["runs"])


def _runs(db) -> dict[str, dict]:
    store = Store(db)
    try:
        (exp,) = store.experiments()
        runs = store.runs_of([exp["id"]])[exp["id"]]
        return {r["id"]: {**r, "data": store.points(r["id"])} for r in runs}
    finally:
        store.close()


@pytest.mark.slow
def test_reproduce_fig3_runs_resumes_and_then_reruns_nothing(tmp_path):
    fig = FIGURES["fig3"]
    url = f"http://127.0.0.1:{free_port()}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    data, out = tmp_path / "data", tmp_path / "out"
    argv = [
        *("reproduce", "fig3", "--episodes", str(EPISODES)),
        *("--seeds", "0", "1", "--arms", *ARMS, "--api", url, "--endpoint", endpoint),
        *("--data-dir", str(data), "--out", str(out), "--quiet", "--quiet-services"),
        # The resume machinery is what is tested here, at async's speed (22 runs); the
        # lockstep default is tests/test_lockstep.py's and the next test's.
        *("--interleave", "async"),
    ]
    t0 = time.monotonic()

    # 1. Interrupted after two runs: it stops the experiment and the cluster.
    first = spawn(*argv, log=tmp_path / "first.log")
    try:
        wait_for(lambda: _completed(url) >= 2, timeout=900, interval=1.0, what="two runs")
    finally:
        first.send_signal(signal.SIGINT)
        first.wait(timeout=120)
    said = (tmp_path / "first.log").read_text()
    assert first.returncode == 1, said
    assert "no API answers" in said and "run the same command again to resume it" in said
    before = _runs(data / "api.sqlite3")
    assert len(before) == len(ARMS) * 2
    done = {r: x for r, x in before.items() if x["status"] == "completed"}
    assert len(done) >= 2 and {x["status"] for x in before.values()} == {"completed", "stopped"}
    assert cluster_processes(endpoint, data) == []

    # 2. The same command: the stopped runs run again (their points go), the rest stay.
    second = macb(*argv, timeout=1500)
    assert second.returncode == 0, second.stderr
    assert f"resuming experiment {next(iter(before.values()))['experiment_id']}" in second.stderr
    retried = len(before) - len(done)
    assert f"queued {retried} run(s) again" in second.stderr
    after = _runs(data / "api.sqlite3")
    assert list(after) == list(before), "the same run ids"
    for run_id, x in after.items():
        assert x["status"] == "completed", x
        assert [p["episode"] for p in x["data"]] == list(range(1, EPISODES + 1)), run_id
        if run_id in done:  # kept as they were
            assert x["data"] == done[run_id]["data"] and x["ended"] == done[run_id]["ended"]
            assert x["attempts"] == 1
        else:
            assert x["attempts"] == 2
    assert cluster_processes(endpoint, data) == []

    # The figure: every arm run, the control included, in the legend and in the report;
    # the arms not asked for are in the report's table with no seeds.
    with Image.open(out / "fig3.png") as png:
        legend = json.loads(png.text["Legend"])
    assert legend == [f"{arm} (2 seeds)" for arm in ARMS]
    md = (out / "fig3.md").read_text()
    arms_table = md.split("## Arms")[1].split("## Claims")[0]
    for arm in fig.arms:
        (line,) = [x for x in arms_table.splitlines() if x.startswith(f"| {arm.name} |")]
        cells = [c.strip() for c in line.strip("| ").split("|")]
        assert cells[3] == (arm.thesis or "not in the thesis (control)")
        if arm.name not in ARMS:
            assert cells[2] == "0", line
            continue
        assert cells[2] == "2", line
        assert cells[4].startswith("plateau ") and f"{EPISODES:,} episodes" in cells[4]
    assert "| beta=0.8 | constant beta=0.8 (control) |" in md
    assert "0 reproduced, 0 not reproduced, 3 not run to that length." in md
    assert f"learner precision fp32 on {len(after)} run(s); CPU" in md  # each learner's report
    assert len(read_points(out / "fig3.csv.gz")) == len(after) * EPISODES
    took = time.monotonic() - t0

    # 3. Once more: nothing runs again, nothing is added.
    third = macb(*argv)
    assert third.returncode == 0, third.stderr
    assert f"{len(after)} completed" in third.stderr and "queued" not in third.stderr
    again = _runs(data / "api.sqlite3")
    assert again == after, "the same runs, points, attempts and times"
    assert cluster_processes(endpoint, data) == []
    print(
        f"fig3 x {EPISODES} episodes x 2 seeds ({len(after)} runs): {took:.0f} s interrupted "
        f"and resumed, {time.monotonic() - t0 - took:.0f} s to find nothing to run"
    )


@pytest.mark.slow  # a whole cluster or campaign run: ~35-55 s alone on 2 cores
def test_reproduce_through_the_cluster_runs_the_thesis_loop_by_default(tmp_path):
    """`macb reproduce` without --local: every run in `interleave: lockstep` (6 episodes:
    past the 100-step warm-up, so there are updates; actions
    from the current weights, computed by the learner), unless --interleave async."""
    url = f"http://127.0.0.1:{free_port()}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    data, out = tmp_path / "data", tmp_path / "out"
    argv = [
        *("reproduce", "fig3", "--episodes", "6"),
        *("--seeds", "0", "--api", url, "--endpoint", endpoint),
        *("--data-dir", str(data), "--out", str(out), "--quiet", "--quiet-services"),
    ]
    done = macb(*argv, timeout=600)
    assert done.returncode == 0, done.stderr
    runs = _runs(data / "api.sqlite3")
    assert len(runs) == len(FIGURES["fig3"].arms)
    for run in runs.values():
        assert run["status"] == "completed", run
        assert run["config"]["interleave"] == "lockstep", run["config"]
        learner = run["services"][run["assign"]["learner"]]
        assert learner["policy_lag"] == 0.0 and learner["replay_ratio"] == 1.0, learner
        # one slot: the figure's runs are one run group
        assert sorted(run["assign"]["group"]) == sorted(runs), run["assign"]
    assert cluster_processes(endpoint, data) == []
    # ... and each is the run the one-process group gives (`--local`), bit for bit
    local = tmp_path / "local"
    argv = [
        *("reproduce", "fig3", "--episodes", "6"),
        *("--seeds", "0", "--local", "--out", str(local), "--quiet"),
    ]
    done = macb(*argv, timeout=600)
    assert done.returncode == 0, done.stderr
    timing = {"steps_per_sec", "train_steps_per_sec", "wall_s", "run", "run_id"}

    def table(path) -> list[dict]:
        rows = read_points(path)
        return sorted(
            ({k: v for k, v in r.items() if k not in timing} for r in rows),
            key=lambda r: (r["arm"], r["seed"], int(r["episode"])),
        )

    cluster_rows, local_rows = table(out / "fig3.csv.gz"), table(local / "fig3.csv.gz")
    assert len(cluster_rows) == len(local_rows) == len(runs) * 6
    assert cluster_rows == local_rows
