"""`macb up --launcher slurm`'s job without a Slurm (tests/test_slurm.py runs it on a real
one): the batch script run by bash with `srun` and `macb` stubbed, so every process it
would start is recorded with its arguments, user and environment; and what is refused
before anything is submitted."""

from __future__ import annotations

import os
import socket
import stat
import subprocess
from pathlib import Path

from cli.reproduce.slurm import SlurmOptions
from cli.slurm_cluster import ClusterJob, render_cluster_script
from cli.supervisor import free_port

# srun: one copy of the command per task, with Slurm's task variables.
SRUN = """#!/bin/bash
n=1; per=1
while [[ $1 == --* ]]; do
  case $1 in --ntasks=*) n=${1#*=} ;; --ntasks-per-node=*) per=${1#*=} ;; esac
  shift
done
for ((i = 0; i < n; i++)); do
  SLURM_PROCID=$i SLURM_NODEID=$((i / per)) "$@" &
done
wait
"""
# macb: records "user|node id|args" a line; the router listens for a moment (or, with
# ROUTER_FAILS set, ends at once, as one that cannot bind its port does).
MACB = """#!/bin/bash
echo "${MACB_ZENOH_USER:-}|${MACB_ZENOH_CONNECT}|${MACB_ZENOH_SECRETS:-}|$*" >> "$RECORD"
if [[ $2 == router ]]; then
  [[ -n ${ROUTER_FAILS:-} ]] && exit 3
  exec python3 -c "import socket,time; s=socket.socket(); s.bind(('127.0.0.1', $PORT)); \
s.listen(); time.sleep(4)"
fi
"""


def executable(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


def run_script(
    tmp_path: Path, job: ClusterJob, head: str | None = None, **more_env: str
) -> tuple[list[list[str]], str, int]:
    """The rendered script run by bash with the stubs: the recorded lines (user,
    connect, secrets, args), the job's own output and its exit code. `head`: what
    `hostname -s` says (the first node's name), this machine's when None."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    executable(bin_dir / "srun", SRUN)
    if head is not None:
        executable(bin_dir / "hostname", f"#!/bin/sh\necho {head}\n")
    macb = executable(bin_dir / "macb stub", MACB)  # (a space: the path stays one word)
    text = render_cluster_script(job, [str(macb)], tmp_path, SlurmOptions("short", "1:00:00"))
    script = tmp_path / "job.sh"
    script.write_text(text)
    record = tmp_path / "record.txt"
    env = {
        **os.environ,
        "PATH": f"{bin_dir}:{os.environ['PATH']}",
        "RECORD": str(record),
        "PORT": str(job.router_port),
        "SLURM_JOB_ID": "77",
        "SLURM_JOB_NODELIST": "cn[1-2]",
        "SLURM_NTASKS": str(job.nodes * job.slots),
        **more_env,
    }
    job.log_dir.mkdir(parents=True, exist_ok=True)
    got = subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, timeout=60)
    said = record.read_text().splitlines() if record.exists() else []
    return [line.split("|", 3) for line in said], got.stdout + got.stderr, got.returncode


def test_one_node_the_router_api_a_counter_and_a_slot_per_task_on_loopback(tmp_path):
    port = free_port()
    job = ClusterJob(1, 2, 1, 1, tmp_path / "data", router_port=port, api_port=8123)
    text = render_cluster_script(job, ["macb"], tmp_path, SlurmOptions("short", "1:00:00"))
    log = f"--output={tmp_path / 'data' / '.slurm'}/cluster-%j.log"
    for line in ("--nodes=1", "--ntasks-per-node=2", "--cpus-per-task=1", "--partition=short",
                 "--time=1:00:00", log):  # fmt: skip
        assert f"#SBATCH {line}\n" in text, line
    lines, out, code = run_script(tmp_path, job)
    args = sorted(line[3] for line in lines)
    data = tmp_path / "data"
    assert args == sorted(
        [
            f"serve router --listen tcp/127.0.0.1:{port}",
            f"serve counter --id counter-n0 --data-dir {data}/counter-n0",
            f"serve slot --actors 1 --id s0 --data-dir {data}/slot-s0",
            f"serve slot --actors 1 --id s1 --data-dir {data}/slot-s1",
            f"serve api --id api --listen-http 127.0.0.1:8123 --data-dir {data}/api",
        ]
    ), out
    assert {line[1] for line in lines} == {f"tcp/127.0.0.1:{port}"}  # one bus, loopback
    assert {line[0] for line in lines} == {""} and {line[2] for line in lines} == {""}
    assert (data / ".slurm" / "77.api").read_text() == "http://127.0.0.1:8123\n"
    host = socket.gethostname().split(".")[0]  # `hostname -s`: where its loopback is
    assert (data / ".slurm" / "77.head").read_text() == f"{host}\n"
    # a part that ends ends the job (Slurm then stops the rest)
    assert code == 1 and "a part of it ended" in out, out


def test_several_nodes_go_on_the_secure_bus_each_service_signed_in_as_its_id(tmp_path):
    port = free_port()
    secrets = tmp_path / "secrets"
    job = ClusterJob(2, 2, 3, 2, tmp_path / "data", port, 8123, secrets, api_public=True)
    lines, out, _ = run_script(tmp_path, job)
    host = socket.gethostname().split(".")[0]  # the batch step's node, `hostname -s`
    by_user = {line[0]: line[3] for line in lines}
    assert by_user["router"] == f"serve router --listen tls/0.0.0.0:{port}"
    assert by_user["api"].startswith("serve api --id api --listen-http 0.0.0.0:8123")
    assert by_user["counter-n0"].startswith("serve counter --id counter-n0")
    assert by_user["counter-n1"].startswith("serve counter --id counter-n1")
    slots = sorted(line[3].split(" --data-dir")[0] for line in lines if line[0] == "")
    assert slots == [f"serve slot --actors 2 --id s{k}" for k in range(4)]  # signs in per child
    assert {line[1] for line in lines} == {f"tls/{host}:{port}"}
    assert {line[2] for line in lines} == {str(secrets)}
    assert job.users()[:4] == ["router", "api", "counter-n0", "counter-n1"]
    assert "actor-s3-1" in job.users() and job.services == len(job.users()) - 1
    assert "#SBATCH --cpus-per-task=3" in render_cluster_script(
        job, ["macb"], tmp_path, SlurmOptions()
    )


def test_what_is_refused_before_submission(tmp_path):
    data = tmp_path / "data"
    assert "give --secrets DIR" in ClusterJob(2, 1, 1, 1, data).error()
    assert ClusterJob(1, 0, 1, 1, data).error() == "--slots must be at least 1, not 0"
    secrets = tmp_path / "secrets"
    assert "cannot read" in ClusterJob(1, 1, 1, 1, data, secrets=secrets).error()
    secrets.mkdir()
    job = ClusterJob(2, 1, 1, 1, data, secrets=secrets)
    (secrets / "users.txt").write_text(
        "\n".join(f"{u}:pw" for u in job.users() if u != "actor-s1") + "\n"
    )
    why = job.error()
    assert "lacks the job's users actor-s1" in why and "--user actor-s1" in why, why
    (secrets / "users.txt").write_text("\n".join(f"{u}:pw" for u in job.users()) + "\n")
    assert job.error() is None
    assert ClusterJob(1, 2, 1, 1, data).error() is None  # one node: loopback, no secrets


def test_macb_up_on_slurm_submits_nothing_without_sbatch(tmp_path):
    from tests.harness import macb

    got = macb(
        "up", "--launcher", "slurm", "--data-dir", str(tmp_path / "d"),
        env={"PATH": "/nonexistent"}, check=False,
    )  # fmt: skip
    assert got.returncode == 2 and "sbatch, squeue, sinfo not found on PATH" in got.stderr
    assert not (tmp_path / "d").exists()
    got = macb("up", "--nodes", "2", check=False)
    assert got.returncode == 2 and "are for --launcher slurm" in got.stderr


def test_both_steps_end_the_job_when_one_of_their_tasks_fails(tmp_path):
    """Under Slurm's default (KillOnBadExit=0) srun waits for a step's other tasks when
    one exits non-zero, so a dead counter or slot would not reach `wait -n`: both steps
    ask for --kill-on-bad-exit=1 (docs/deploy.md says the job then ends)."""
    for nodes, secrets in ((1, None), (2, tmp_path / "secrets")):
        job = ClusterJob(nodes, 2, 1, 1, tmp_path / "data", secrets=secrets)
        text = render_cluster_script(job, ["macb"], tmp_path, SlurmOptions())
        steps = [line for line in text.splitlines() if line.startswith("srun ")]
        assert len(steps) == 2, text
        assert all(" --kill-on-bad-exit=1 " in step for step in steps), steps


def test_a_taken_port_on_the_first_node_starts_nothing_naming_it(tmp_path):
    """The router's or the API's port answering before the router starts (another
    cluster, anyone's process): the job ends at once, exit 2, naming the port, and
    starts nothing, instead of every check passing against the other listener."""
    for taken in ("router", "api"):
        folder = tmp_path / taken
        folder.mkdir()
        router, api = free_port(), free_port()
        job = ClusterJob(1, 1, 1, 1, folder / "data", router_port=router, api_port=api)
        with socket.socket() as held:
            held.bind(("127.0.0.1", router if taken == "router" else api))
            held.listen()
            lines, out, code = run_script(folder, job)
        port = router if taken == "router" else api
        assert code == 2 and f"port {port} on " in out and "something listens" in out, out
        assert lines == [], f"nothing starts: {lines}"


def test_a_port_taken_on_the_first_nodes_own_address_stops_a_service_on_every_address(tmp_path):
    """A router or public API listens on every address: a listener on the first node's
    own address alone (here 127.0.0.2, the node's name as `hostname -s` gives it) does
    not answer on 127.0.0.1, so the job probes the node's name too and ends, exit 2;
    a service on loopback alone is not refused for it."""
    for taken in ("router", "api", "loopback"):
        folder = tmp_path / taken
        folder.mkdir()
        router, api = free_port(), free_port()
        nodes = 2 if taken == "router" else 1
        job = ClusterJob(nodes, 1, 1, 1, folder / "data", router_port=router, api_port=api,
                         api_public=taken == "api")  # fmt: skip
        port = router if taken == "router" else api
        with socket.socket() as held:
            held.bind(("127.0.0.2", port))
            held.listen()
            lines, out, code = run_script(folder, job, head="127.0.0.2", ROUTER_FAILS="1")
        if taken == "loopback":
            assert "in use" not in out and lines, out  # it went on to start the router
            continue
        assert code == 2 and f"port {port} on 127.0.0.2 is in use" in out, out
        assert lines == [], f"nothing starts: {lines}"


def test_a_router_that_ends_before_it_listens_ends_the_job(tmp_path):
    """The router process gone (it could not bind, say): the job ends at once, exit 1,
    rather than waiting a minute and starting the services on a port that may be
    someone else's."""
    job = ClusterJob(1, 1, 1, 1, tmp_path / "data", router_port=free_port(), api_port=free_port())
    lines, out, code = run_script(tmp_path, job, ROUTER_FAILS="1")
    assert code == 1 and "the router did not listen" in out, out
    assert [line[3].split()[1] for line in lines] == ["router"], lines


# ---------------------------------------------------------------- following the job
def squeue_says(state: str):
    """A stand-in for `squeue -j JOB -o %T|%r` saying `state`."""
    return lambda argv: subprocess.CompletedProcess(argv, 0, f"{state}|None\n", "")


def job_files(tmp_path: Path, url: str, head: str) -> ClusterJob:
    """A one-node job whose batch step has written its API's address and its node."""
    job = ClusterJob(1, 1, 1, 1, tmp_path / "data")
    job.log_dir.mkdir(parents=True)
    (job.log_dir / "77.api").write_text(url + "\n")
    (job.log_dir / "77.head").write_text(head + "\n")
    return job


def test_a_loopback_api_is_polled_only_from_its_own_node():
    from cli.slurm_cluster import loopback_elsewhere

    assert loopback_elsewhere("http://127.0.0.1:8000", "cn07", "login1")
    assert loopback_elsewhere("http://localhost:8000", "cn07", "login1.example.org")
    assert not loopback_elsewhere("http://127.0.0.1:8000", "cn07", "cn07")
    assert not loopback_elsewhere("http://127.0.0.1:8000", "cn07", "cn07.cluster.local")
    assert not loopback_elsewhere("http://cn07:8000", "cn07", "login1")  # a token: the network


def test_an_api_on_another_nodes_loopback_is_not_polled_here_how_to_reach_it_is_said(
    tmp_path, capsys
):
    """No token: the API listens on 127.0.0.1 of the job's first node. From a login node
    127.0.0.1 is not the job's: nothing is polled (a listener there is not touched), the
    command says how to reach it and returns 0, the job running."""
    from cli.slurm_cluster import wait_until_up

    port = free_port()
    with socket.socket() as stranger:  # this host's 127.0.0.1:port: not the job's API
        stranger.bind(("127.0.0.1", port))
        stranger.listen()
        stranger.settimeout(0.5)
        job = job_files(tmp_path, f"http://127.0.0.1:{port}", "cn07")
        code = wait_until_up("77", job, tmp_path / "log", 30, squeue_says("RUNNING"), "login1")
        try:
            stranger.accept()[0].close()
            asked = True
        except TimeoutError:
            asked = False
    err = capsys.readouterr().err
    assert code == 0 and not asked, err
    assert f"ssh -N -L {port}:127.0.0.1:{port} cn07" in err and "MACB_API_TOKEN" in err
    assert f"MACB_API_URL=http://127.0.0.1:{port}" in err and "scancel 77" in err


def test_the_api_is_asked_with_the_token_and_a_refusal_is_told_apart(
    tmp_path, router, monkeypatch, capsys
):
    """MACB_API_TOKEN set: the API (uvicorn, TokenAuth) wants the bearer token on
    /workers; it is sent, and a wrong one ends the wait at once saying so, and that the
    job still runs (scancel), instead of polling to the timeout."""
    from cli.slurm_cluster import services_answering, wait_until_up
    from services.api.client import ApiClient, ApiError
    from tests.harness import start_api

    server = start_api(tmp_path, router, token="s3cret")
    try:
        monkeypatch.setenv("MACB_API_TOKEN", "s3cret")
        with ApiClient(server.url) as api:  # the token from the environment
            assert services_answering(api) is not None
        with ApiClient(server.url, token="wrong") as api:
            try:
                services_answering(api)
                raise AssertionError("a wrong token is not refused")
            except ApiError as err:
                assert err.status == 401
        monkeypatch.setenv("MACB_API_TOKEN", "wrong")
        here = socket.gethostname().split(".")[0]
        job = job_files(tmp_path, server.url, here)
        code = wait_until_up("77", job, tmp_path / "log", 60, squeue_says("RUNNING"), here)
    finally:
        server.stop()
    err = capsys.readouterr().err
    assert code == 1 and "HTTP 401" in err and "MACB_API_TOKEN" in err, err
    assert "scancel 77" in err and "not up within" not in err, err


def test_giving_up_says_the_job_is_left_running_and_how_to_cancel_it(tmp_path, capsys):
    from cli.slurm_cluster import wait_until_up

    job = ClusterJob(1, 1, 1, 1, tmp_path / "data")
    code = wait_until_up("77", job, tmp_path / "log", 0.5, squeue_says("PENDING"), "login1")
    err = capsys.readouterr().err
    assert code == 1 and "not up within 0 s" in err and "last seen PENDING" in err, err
    assert "scancel 77" in err, err


def squeue_answers(*answers: tuple[int, str, str]):
    """A stand-in for squeue giving (exit code, stdout, stderr) in turn, the last one
    again once they run out; the calls are counted in its `calls`."""
    calls: list[list[str]] = []

    def run(argv):
        calls.append(list(argv))
        code, out, err = answers[min(len(calls), len(answers)) - 1]
        return subprocess.CompletedProcess(argv, code, out, err)

    run.calls = calls  # type: ignore[attr-defined]
    return run


BUSY = (1, "", "squeue: error: slurm_load_jobs error: Socket timed out on send/recv operation")


def test_a_busy_controller_is_asked_again_and_only_an_unknown_job_is_gone(
    tmp_path, monkeypatch, capsys
):
    """squeue failing says nothing of the job (a busy controller times out): `macb up
    --launcher slurm` once took the first failure for the job's end, exit 1, while it
    ran. It asks again, saying so; the job is gone only when squeue lists nothing or
    says "Invalid job id specified"; squeue failing every time ends the wait saying the
    job's state is unknown, not that it ended."""
    import cli.slurm_cluster as sc
    from cli.slurm_cluster import wait_until_up

    monkeypatch.setattr(sc, "SQUEUE_RETRY_S", 0.0)
    job = job_files(tmp_path, "http://127.0.0.1:8123", "cn07")
    run = squeue_answers(BUSY, BUSY, (0, "RUNNING|None\n", ""))
    assert wait_until_up("77", job, tmp_path / "log", 30, run, "login1") == 0
    err = capsys.readouterr().err
    assert err.count("squeue failed (squeue: error: slurm_load_jobs error: Socket") == 2, err
    assert "ended" not in err and "ssh -N -L 8123:127.0.0.1:8123 cn07" in err, err

    run = squeue_answers(BUSY)
    assert wait_until_up("77", job, tmp_path / "log", 30, run, "login1") == 1
    err = capsys.readouterr().err
    assert len(run.calls) == sc.SQUEUE_TRIES and "ended" not in err, err
    assert "where it stands is unknown: squeue failed 6 times" in err and "scancel 77" in err

    gone = (1, "", "slurm_load_jobs error: Invalid job id specified")
    for answers in ((gone,), ((0, "", ""),)):
        run = squeue_answers(*answers)
        assert wait_until_up("77", job, tmp_path / "log", 30, run, "login1") == 1
        assert "cluster job 77 ended (gone)" in capsys.readouterr().err and len(run.calls) == 1


def test_flags_the_job_fixes_itself_are_refused_not_ignored(tmp_path):
    """The job always runs the API and places its router itself: `--no-api` and an
    --endpoint host were taken and ignored (the job started the API, the router listened
    on loopback). They are refused before anything is written or submitted."""
    from tests.harness import macb

    data = tmp_path / "d"
    for flags, says in [
        (["--no-api"], "--no-api: the job always runs the API"),
        (["--endpoint", "tcp/10.1.2.3:7447"], "--endpoint tcp/10.1.2.3:7447: the job's router"),
    ]:
        got = macb("up", "--launcher", "slurm", "--data-dir", str(data), "--detach", *flags,
                   env={"PATH": "/nonexistent"})  # fmt: skip
        assert got.returncode == 2 and says in got.stderr, got.stderr
        assert not data.exists()


def test_a_requeued_job_appends_to_its_log(tmp_path):
    """Slurm requeues a batch job by default when its node fails; the cluster job's log
    is opened for appending, so the failed attempt's lines stay (the default truncates)."""
    from tests.test_slurm_launcher import sbatch_reads

    job = ClusterJob(1, 1, 1, 1, tmp_path / "data")
    argv = sbatch_reads(render_cluster_script(job, ["macb"], tmp_path, SlurmOptions()))
    assert "--open-mode=append" in argv, argv
