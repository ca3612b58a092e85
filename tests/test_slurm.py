"""`macb reproduce --local --launcher slurm` on a real Slurm (`make test-slurm`): a
one-node Slurm of Debian's slurm-wlm and munge started for these tests
(tests/slurm_node.py), the figure's groups submitted as an array job, Slurm's own
`scontrol requeue` and `scancel` on its tasks, and input refused before submission.

Without Slurm installed the tests skip, saying why; `make test-slurm` sets
MACB_SLURM_SETUP=1, which lets them install munge and slurm-wlm (as root).
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from cli.results import read_points
from tests import slurm_node
from tests.harness import macb, spawn, wait_for

pytestmark = [pytest.mark.slurm, pytest.mark.timeout(900)]

SETUP = os.environ.get("MACB_SLURM_SETUP") == "1"
TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")


@pytest.fixture(scope="module")
def node(tmp_path_factory) -> Iterator[slurm_node.Node]:
    t0 = time.monotonic()
    try:
        n = slurm_node.start(tmp_path_factory.mktemp("slurm"), may_set_up=SETUP)
    except slurm_node.Unavailable as err:
        pytest.skip(f"no Slurm for these tests: {err}")
    print(f"\none-node Slurm up in {time.monotonic() - t0:.1f} s ({n.env['SLURM_CONF']})")
    try:
        yield n
    finally:
        n.stop()


def on(node: slurm_node.Node, *args: str, **env: str) -> subprocess.CompletedProcess:
    """`macb ARGS` talking to this Slurm."""
    return macb(*args, env={"SLURM_CONF": node.env["SLURM_CONF"], **env}, timeout=600)


def table(path: Path) -> list[dict[str, str]]:
    return [{k: v for k, v in r.items() if k not in TIMING} for r in read_points(path)]


def rows(folder: Path) -> list[dict]:
    lines = (folder / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(x).items() if k not in TIMING} for x in lines]


def jobs(node: slurm_node.Node) -> list[str]:
    got = node.run("squeue", "-h", "-r", "-t", "all", "-o", "%i")
    assert got.returncode == 0, got.stderr
    return sorted(got.stdout.split())


def test_fig3_on_slurm_writes_the_csv_of_the_local_launcher(node, tmp_path):
    fig3 = ["reproduce", "fig3", "--episodes", "6", "--local", "--quiet"]
    got = on(node, *fig3, "--launcher", "slurm", "--out", str(tmp_path / "slurm"))
    assert got.returncode == 0, got.stderr + node.logs()
    assert "2 task(s)" in got.stderr and "33 completed" in got.stderr, got.stderr
    record = json.loads((tmp_path / "slurm" / "runs" / ".slurm" / "jobs.json").read_text())
    (sub,) = record["submissions"]
    assert sorted(r for t in sub["tasks"] for r in t["runs"]) == sorted(
        p.name for p in (tmp_path / "slurm" / "runs").iterdir() if not p.name.startswith(".")
    )
    for t in sub["tasks"]:  # each task ran on Slurm, its log in the runs folder
        log = tmp_path / "slurm" / "runs" / ".slurm" / f"{sub['job']}_{t['index']}.log"
        assert f"task {t['index']} on " in log.read_text()
    local = on(node, *fig3, "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr
    assert table(tmp_path / "slurm" / "fig3.csv.gz") == table(tmp_path / "local" / "fig3.csv.gz")
    assert "--launcher slurm" in (tmp_path / "slurm" / "fig3.md").read_text()


def test_a_requeued_task_resumes_from_its_cut_and_a_cancelled_one_is_named_then_completed(
    node, tmp_path
):
    out = tmp_path / "slurm"
    # Two runs (an arm and its control), two groups of one: two tasks side by side.
    args = ["reproduce", "fig3", "--episodes", "80", "--seeds", "0", "--local", "--quiet",
            "--arms", "beta=0.8", "CONSTANT beta=0.8*", "--jobs", "2"]  # fmt: skip
    names = ["beta_0.8-s0", "constant_beta_0.8_control-s0"]
    log = tmp_path / "follow.log"
    proc = spawn(*args, "--launcher", "slurm", "--out", str(out), log=log, env=node.env)
    try:
        # Both runs past their first cut (each run cuts its first point), mid-run.
        def cut_and_rows() -> bool:
            return all(
                list((out / "runs" / n / "cuts").glob("cut-*.pt"))
                and len((out / "runs" / n / "metrics.jsonl").read_text().splitlines()) >= 3
                for n in names
            )

        wait_for(cut_and_rows, timeout=240, interval=0.2, what="both runs past a cut")
        (sub,) = json.loads((out / "runs" / ".slurm" / "jobs.json").read_text())["submissions"]
        task = {t["runs"][0]: f"{sub['job']}_{t['index']}" for t in sub["tasks"]}
        requeue = node.run("scontrol", "requeue", task[names[0]])
        assert requeue.returncode == 0, requeue.stderr
        cancel = node.run("scancel", task[names[1]])
        assert cancel.returncode == 0, cancel.stderr
        mid = [len(rows(out / "runs" / n)) for n in names]
        assert max(mid) < 80, f"requeued too late to test anything: {mid}"
        # Slurm holds a requeued batch job for two minutes (its begin time); let it go now.
        wait_for(
            lambda: node.run("scontrol", "update", f"JobId={task[names[0]]}", "StartTime=now")
            .returncode == 0,
            timeout=30, interval=0.5, what="the requeued task pending again",
        )  # fmt: skip
        assert proc.wait(timeout=400) == 1
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    followed = log.read_text()
    first_log = (out / "runs" / ".slurm" / f"{task[names[0]]}.log").read_text()
    assert "restart 1" in first_log and "resuming from cut-" in first_log, first_log
    assert len(rows(out / "runs" / names[0])) == 80
    # The cancelled group: reported incomplete, by name, with what Slurm says.
    assert f"[job {task[names[1]]}]: incomplete (CANCELLED)" in followed, followed
    assert f"runs: {names[1]}" in followed and "1 group(s) incomplete" in followed
    assert not (out / "fig3.md").exists()
    again = on(node, *args, "--launcher", "slurm", "--out", str(out))
    assert again.returncode == 0, again.stderr
    assert f"[job {task[names[1]]}]: incomplete (CANCELLED)" in again.stderr
    assert "submitting its 1 unfinished run(s) again" in again.stderr
    assert "resumes from cut-" in again.stderr and "2 completed" in again.stderr, again.stderr
    # Both runs' rows equal those of the same runs trained straight through, without Slurm.
    straight = on(node, *args, "--out", str(tmp_path / "straight"))
    assert straight.returncode == 0, straight.stderr
    for n in names:
        assert rows(out / "runs" / n) == rows(tmp_path / "straight" / "runs" / n), n


@pytest.fixture
def unwritable(tmp_path) -> Iterator[Path]:
    """A folder this process cannot write in: read-only mounted for root (whom
    permissions do not stop), mode 0555 for anyone else."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    got = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(folder)],
                         capture_output=True, text=True)  # fmt: skip
    if got.returncode:
        pytest.skip(f"cannot mount a read-only folder here: {got.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def test_bad_input_is_refused_before_anything_is_submitted(node, tmp_path, unwritable):
    before = jobs(node)
    fig3 = ["reproduce", "fig3", "--episodes", "2", "--local", "--launcher", "slurm"]
    cases = [
        ({"PATH": "/nonexistent"}, [], "sbatch, squeue, sinfo not found on PATH"),
        ({}, ["--partition", "gpu"], "--partition gpu: no such partition (sinfo lists: macbtest)"),
        ({}, ["--runs", str(unwritable / "runs")],
         f"the runs folder {unwritable / 'runs'} is not writable"),
    ]  # fmt: skip
    for i, (env, flags, message) in enumerate(cases):
        out = tmp_path / f"out{i}"
        got = on(node, *fig3, "--out", str(out), *flags, **env)
        assert got.returncode == 2 and message in got.stderr, (flags, got.stderr)
        assert not out.exists(), flags
    assert jobs(node) == before


def test_the_service_cluster_job_runs_an_experiment_posted_to_its_api_then_scancel_ends_it(
    node, tmp_path
):
    """`macb up --launcher slurm`: one job, the router, a counter and the API on its node
    and a worker slot per task (srun); a two-seed experiment posted over REST runs on
    both slots, counted by the node's counter, exactly; scancel leaves nothing running."""
    import httpx

    from cli.supervisor import free_port
    from tests.harness import TINY, processes_with

    data, port, api_port = tmp_path / "cluster", free_port(), free_port()
    where = ["--endpoint", f"tcp/127.0.0.1:{port}", "--api-port", str(api_port)]
    up = on(node, "up", "--launcher", "slurm", "--slots", "2", "--data-dir", str(data), *where)
    assert "cluster job " in up.stderr, up.stderr
    job = up.stderr.split("cluster job ", 1)[1].split()[0]
    try:
        assert up.returncode == 0, up.stderr + node.logs()
        url = up.stdout.strip().splitlines()[-1]
        assert url == f"http://127.0.0.1:{api_port}" and f"scancel {job}" in up.stderr
        workers = httpx.get(f"{url}/workers").json()["workers"]
        host = subprocess.check_output(["hostname", "-s"], text=True).strip()
        assert sorted((w["id"], w["node"]) for w in workers if w["answers"]) == sorted(
            (sid, host)
            for sid in ("api", "counter-n0", "learner-s0", "learner-s1", "evaluator-s0",
                        "evaluator-s1", "actor-s0", "actor-s1")
        ), workers  # fmt: skip
        exp = httpx.post(f"{url}/experiments", json={**TINY, "seeds": [0, 1]}).json()
        runs = [r["id"] for r in exp["runs"]]

        def ended() -> dict | None:
            got = httpx.get(f"{url}/experiments/{exp['id']}").json()
            return got if got["status"] not in ("queued", "running") else None

        final = wait_for(ended, timeout=300, interval=1, what="the experiment's end")
        assert final["status"] == "completed", final
        records = [httpx.get(f"{url}/runs/{r}").json() for r in runs]
        assert {r["assign"]["learner"] for r in records} == {"learner-s0", "learner-s1"}
        for r in records:  # exact: counted == collected == ingested, by the node's counter
            assert r["assign"]["counter"] == "counter-n0", r["assign"]
            collected = TINY["episodes"] * 20
            assert r["services"]["counter-n0"]["counted_transitions"] == collected
            assert r["services"][r["assign"]["learner"]]["ingested"] == collected
            actor = r["assign"]["actors"][0]
            assert r["services"][actor]["final_seq"] == collected and r["points"] == 3
    finally:
        cancel = node.run("scancel", job)
    assert cancel.returncode == 0, cancel.stderr
    wait_for(
        lambda: node.run("squeue", "-h", "-j", job, "-t", "all", "-o", "%T").stdout.strip()
        == "CANCELLED",
        timeout=60, interval=0.5, what="the job cancelled",
    )  # fmt: skip
    # Nothing of it left: no process with its data dir or its router's port.
    wait_for(
        lambda: not processes_with(str(data)) and not processes_with(f"127.0.0.1:{port}"),
        timeout=60, interval=0.5, what="every process of the job ended",
    )  # fmt: skip


def test_the_throughput_benchmark_runs_both_launchers_and_sees_the_tasks_run_at_once(
    node, tmp_path
):
    """benchmarks/bench_slurm.py with a tiny setting on this Slurm (timings not asserted):
    one round of A B, both rates and ratios written, the Slurm side's two tasks at once."""
    import sys

    from tests.harness import ROOT

    out = tmp_path / "slurm.json"
    bench = str(ROOT / "benchmarks" / "bench_slurm.py")
    argv = [sys.executable, bench, "--episodes", "3", "--arms", "sparse", "sparse + cen-macb",
            "--rounds", "1", "--out", str(out)]  # fmt: skip
    got = subprocess.run(argv, env=node.env, capture_output=True, text=True, timeout=600)
    assert got.returncode == 0, got.stderr[-3000:]
    assert "the Slurm this environment reaches" in got.stderr, got.stderr
    result = json.loads(out.read_text())
    (local,), (slurm,) = result["rounds"]["local"], result["rounds"]["slurm"]
    assert local["runs"] == slurm["runs"] == 6 and local["env_steps"] == slurm["env_steps"]
    assert slurm["tasks"] == 2 and slurm["concurrent"], slurm
    assert set(result["ratio"]) == {"command", "train"} and result["cpu"]
    assert "| command |" in got.stdout and "slurm / local" in got.stdout
