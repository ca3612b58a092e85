"""`macb up`: the whole local cluster as processes, a run on it, and a clean shutdown."""

from __future__ import annotations

import csv
import json
import signal
import socket
import time
from pathlib import Path

import pytest

from cli.supervisor import free_port
from shared import procs
from shared.core.learners.precision import native_bf16
from shared.persist import provenance
from tests.harness import (
    ROOT,
    TINY,
    Cluster,
    cluster_processes,
    macb,
    parents,
    wait_for,
    wait_port,
    wait_services,
    write_config,
)


def test_up_runs_an_experiment_and_leaves_nothing_running(tmp_path):
    """Asked for bf16, which runs where the CPU has it: out/provenance.json, as the
    learner reported it, says which precision ran."""
    cfg = write_config(tmp_path / "tiny.yaml", {**TINY, "precision": "bf16"})
    with Cluster(tmp_path) as cluster:
        cluster.up("--quiet", "--run", str(cfg), "--out", str(tmp_path / "out"))
        code, out = cluster.wait(timeout=240)
        assert code == 0, out
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
        assert (
            start["learner"]["precision_asked"] == "bf16" and start["learner"]["precision"] == ran
        )
        assert "dashboard" in out and (tmp_path / "data" / "api.sqlite3").exists()
        for name in ("router", "counter", "learner", "evaluator", "actor0", "api"):
            assert (tmp_path / "data" / "logs" / f"{name}.log").exists()
        assert cluster.leftovers() == []


@pytest.mark.slow  # a whole cluster or campaign run: ~35-55 s alone on 2 cores
def test_slots_run_two_runs_at_once_each_exact(tmp_path):
    """`macb up --slots 2`: two learners and evaluators, two actors, one counter; an
    experiment of two seeds has both runs running at once, and each is exact."""
    import sqlite3

    cfg = write_config(tmp_path / "tiny.yaml", {**TINY, "episodes": 40})
    run = ("--run", str(cfg), "--seeds", "0", "1", "--out", str(tmp_path / "out"))
    with Cluster(tmp_path) as cluster:
        cluster.up("--quiet", "--slots", "2", *run)
        code, out = cluster.wait(timeout=300)
        assert code == 0, out
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
        assert cluster.leftovers() == []


def test_sigterm_stops_every_service_and_the_router(tmp_path):
    with Cluster(tmp_path) as cluster:
        cluster.up("--quiet")
        with _client(cluster.endpoint) as bus:
            wait_services(bus, 4, timeout=90)
        children = cluster.leftovers()
        assert len(children) >= 5, f"router and four services run as processes: {children}"
        cluster.procs["up"].send_signal(signal.SIGTERM)
        code, out = cluster.wait(timeout=60)
        assert code == 0, out
        assert "cluster stopped" in out
        deadline = time.monotonic() + 5
        while cluster.leftovers() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert cluster.leftovers() == [], "no orphan process"


def _children(pid: int, marker: str) -> list[int]:
    """Live PIDs whose parent is `pid` and whose command line (its words joined by
    spaces, as a forked service's title has them) holds `marker`."""
    return [
        child
        for child, parent in parents().items()
        if parent == pid and marker in " ".join(procs.cmdline(child) or [])
    ]


@pytest.mark.parametrize("fork_server", ["1", "0"])
def test_a_killed_macb_up_takes_every_service_with_it(tmp_path, fork_server):
    """SIGKILL of `macb up` (no handler of its own runs; the OOM killer, `kill -9`): the
    router, the API and every service die with it (PR_SET_PDEATHSIG, armed by each child
    from MACB_PARENT_PID), so none goes on holding its port and writing the data dir;
    with its services forked from its fork server (cli/forkserver.py), or not, and the
    server dies with it too."""
    with Cluster(tmp_path, env={"MACB_FORK_SERVER": fork_server}) as cluster:
        cluster.up("--quiet", answering=5)  # the API, counter, learner, evaluator, actor0
        pids = cluster.pids()
        assert sorted(pids) == ["actor0", "api", "counter", "evaluator", "learner", "router"]
        up = cluster.procs["up"].pid
        servers = _children(up, "cli.forkserver")
        assert len(servers) == (fork_server == "1"), servers
        assert sorted(_children(up, "-m cli serve ")) == sorted(pids.values())  # each up's child
        cluster.procs["up"].kill()
        cluster.procs["up"].wait(timeout=30)
        deadline = time.monotonic() + 5
        while (alive := [n for n, pid in pids.items() if procs.alive(pid)]) and (
            time.monotonic() < deadline
        ):
            time.sleep(0.1)
        assert alive == [], f"outlived a killed macb up: {alive}"
        assert cluster.leftovers() == []
        wait_for(lambda: not any(procs.alive(s) for s in servers), 10, what="the server's end")


def test_up_refuses_a_port_someone_listens_on_naming_it_and_starts_nothing(tmp_path):
    """7447 or 8000 taken (another `macb up`, compose, anyone's process): exit 2 naming
    the port before any process starts, rather than a cluster whose router and API fail
    to bind while the other listener answers every check. An endpoint or port that is
    none is refused too, exit 2, naming it (it was a traceback)."""
    for taken in ("--endpoint", "--api-port"):
        data, router, api = tmp_path / taken.strip("-"), free_port(), free_port()
        port = router if taken == "--endpoint" else api
        with socket.socket() as held:
            held.bind(("127.0.0.1", port))
            held.listen()
            got = macb("up", "--endpoint", f"tcp/127.0.0.1:{router}", "--api-port", str(api),
                       "--data-dir", str(data), timeout=120)  # fmt: skip
        assert got.returncode == 2, got.stderr[-3000:]
        assert f"port {port} on 127.0.0.1 is in use: something listens on it" in got.stderr
        assert not (data / "logs").exists() and not (data / "cluster.json").exists()
        assert cluster_processes(f"tcp/127.0.0.1:{router}", data) == []
    endpoint = ["--endpoint", f"tcp/127.0.0.1:{free_port()}"]
    api_port = ["--api-port", str(free_port())]
    for bad, said in (  # (each beside a port of its own: never 7447 or 8000)
        (["--endpoint", "tcp/127.0.0.1", *api_port], "'tcp/127.0.0.1' is not HOST:PORT"),
        (["--endpoint", "tcp/127.0.0.1:70000", *api_port], "with a port from 1 to 65535"),
        ([*endpoint, "--api-port", "70000"], "--api-port must be from 1 to 65535, not 70000"),
    ):
        got = macb("up", *bad, "--data-dir", str(tmp_path / "bad"), timeout=120)
        assert got.returncode == 2 and said in got.stderr, got.stderr[-3000:]
        assert "Traceback" not in got.stderr and not (tmp_path / "bad").exists()


def _client(endpoint):
    wait_port(endpoint, timeout=30)
    from shared.net.bus import Bus

    return Bus([endpoint])


# ---------------------------------------------------------------- `make run`
TIMING = {"steps_per_sec", "train_steps_per_sec", "wall_s"}


def make_run_args() -> list[str]:
    """`make run`'s `macb up` arguments, read from the Makefile (so this tests what a
    newcomer runs), without the folders the test gives its own."""
    recipe = (ROOT / "Makefile").read_text().split("\nrun: ", 1)[1].splitlines()[1]
    args = recipe.split("macb up ", 1)[1].split()
    for flag in ("--out", "--data-dir"):
        i = args.index(flag)
        del args[i : i + 2]
    return args


def rows_of(path: Path) -> list[dict]:
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def test_make_run_gives_the_same_rows_every_time_and_macb_trains(tmp_path):
    """`make run`'s experiment (configs/default.yaml through the API of `macb up`), cut
    to 30 episodes, gives `macb train`'s rows with the same config, and its output says
    what was learned. `macb train` is a pure function of its config (tests/test_trainer.py's
    test_same_seed_same_metrics_different_seed_different), so a cluster run equal to it
    is the same rows every time."""
    args = make_run_args()
    assert args == ["--run", "configs/default.yaml", "--quiet-services"], args
    with Cluster(tmp_path) as cluster:
        cluster.up(*args, "--episodes", "30", "--out", str(tmp_path / "default"))
        code, out = cluster.wait(timeout=300)
        assert code == 0, out
        assert cluster.leftovers() == []
    line = [x for x in out.splitlines() if x.startswith("what was learned")]
    assert len(line) == 1 and "at episode 30" in line[0], out
    ran = rows_of(tmp_path / "default" / "metrics.jsonl")
    assert [r["episode"] for r in ran] == [10, 20, 30]
    macb("train", "--config", str(ROOT / "configs/default.yaml"), "--episodes", "30",
         "--out", str(tmp_path / "train"), "--quiet", check=True)  # fmt: skip
    trained = rows_of(tmp_path / "train" / "metrics.jsonl")
    assert len(trained) == 3
    assert [{k: c[k] for k in t if k in c} for c, t in zip(ran, trained)] == trained, (
        "make run's rows are not macb train's"
    )


@pytest.mark.slow
def test_make_runs_experiment_learns(tmp_path):
    """configs/default.yaml whole, as `macb train` runs it (the rows `make run` gives, by
    the test above): no success in its first 100 episodes, every one at its end. Its rows
    are one CPU kind's rounding (docs/reliability.md): the Xeon's succeed every time from
    episode 360, an AMD EPYC (Zen 3)'s from 390 (0.8, 0.8, 0.9 before), so the end is
    held to a mean over its last 5 points and its last point."""
    macb("train", "--config", str(ROOT / "configs/default.yaml"), "--out", str(tmp_path),
         "--quiet", check=True, timeout=900)  # fmt: skip
    rows = rows_of(tmp_path / "metrics.jsonl")
    assert [r["episode"] for r in rows] == list(range(10, 401, 10))
    assert max(r["success_rate"] for r in rows[:10]) <= 0.2
    end = [r["success_rate"] for r in rows[-5:]]
    assert sum(end) / 5 >= 0.8 and end[-1] == 1.0, end
