"""cli/forkserver.py: services forked from one process that has loaded torch behave as
the `python -m cli serve ...` interpreters they stand in for: our children, in sessions
of their own, titled as that command, each with its own environment, output and exit
code; a service whose loading variables differ, or MACB_FORK_SERVER=0, gets its own
interpreter; the server dies with its client. Real routers on loopback ports."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from cli import forkserver
from cli.forkserver import Forked, ForkServer, start_cli
from cli.supervisor import free_port, wait_port
from shared import procs
from tests.harness import ROOT, Cluster, _environ, parents, wait_for


def _router(server: ForkServer, env: dict, log: Path, user: str) -> tuple[Forked, str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    args = ["serve", "router", "--listen", endpoint]
    mine = {"MACB_ZENOH_USER": f"router-{user}", "MACB_ZENOH_PASSWORD": "pw"}  # its id
    p = server.start(args, {**env, **mine}, ROOT, log)
    wait_port(endpoint, proc=p)
    return p, endpoint


def test_a_forked_service_is_our_child_in_its_own_session_with_its_own_environment(tmp_path):
    env = _environ(None)
    server = ForkServer(env)
    try:
        alpha, where = _router(server, env, tmp_path / "alpha.log", "alpha")
        beta, _ = _router(server, env, tmp_path / "beta.log", "beta")
        # A subreaper only while it starts one: an orphan of ours goes to init, as before.
        assert not forkserver.subreaper()
        for p in (alpha, beta):
            assert parents()[p.pid] == os.getpid()  # ours to wait for, not the server's
            assert os.getsid(p.pid) == p.pid  # a session of its own, as procs.start gives
            assert procs.names_one_of(p.pid, ["-m cli serve router --listen"])
        assert procs.names_one_of(alpha.pid, [where.rsplit(":", 1)[1]])
        wait_for(lambda: "router router-alpha listening" in (tmp_path / "alpha.log").read_text())
        wait_for(lambda: "router router-beta listening" in (tmp_path / "beta.log").read_text())
        assert alpha.poll() is None and beta.poll() is None
        alpha.terminate()
        beta.kill()
        assert alpha.wait(timeout=30) == 0  # a router's clean stop
        assert beta.wait(timeout=30) == -signal.SIGKILL
        assert "router stopped" in (tmp_path / "alpha.log").read_text()
        beta.kill()  # reaped already: nothing is signalled
        # A command it refuses exits as it would anywhere: argparse's 2, its message logged.
        bad = server.start(["serve", "router", "--listen"], env, ROOT, tmp_path / "bad.log")
        assert bad.wait(timeout=30) == 2
        assert "expected one argument" in (tmp_path / "bad.log").read_text()
    finally:
        server.close()
    assert server.proc.returncode is not None


def test_a_service_that_may_not_be_forked_gets_its_own_interpreter(tmp_path):
    env = _environ(None)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    args = ["serve", "router", "--listen", endpoint]
    cases = {
        "threads": {**env, "OMP_NUM_THREADS": "2"},  # read by libgomp as torch loads
        "off": {**env, "MACB_FORK_SERVER": "0"},
    }
    for name, case in cases.items():
        p = start_cli(args, case, cwd=ROOT, log=tmp_path / f"{name}.log")
        try:
            assert isinstance(p, subprocess.Popen), name
            wait_port(endpoint, proc=p)
        finally:
            procs.end(p, 10)
    forked = start_cli(args, env, cwd=ROOT, log=tmp_path / "forked.log")
    try:
        assert isinstance(forked, Forked)
        wait_port(endpoint, proc=forked)
    finally:
        procs.end(forked, 10)
    assert forked.returncode == 0


def test_the_tests_clusters_fork_their_services(tmp_path):
    """The harness starts services through the server (what makes `make test` shorter);
    this fails if it quietly went back to an interpreter per service."""
    with Cluster(tmp_path) as cluster:
        cluster.router()
        assert isinstance(cluster.procs["router"], Forked)
        assert forkserver._SHARED is not None and forkserver._REFUSED is None


CLIENT = """
import os, sys, time
from cli.forkserver import ForkServer
server = ForkServer(dict(os.environ))
print(server.proc.pid, flush=True)
time.sleep(120)
"""


def test_the_server_dies_with_its_client(tmp_path):
    log = tmp_path / "client.log"
    client = procs.start([sys.executable, "-c", CLIENT], log=log, cwd=ROOT)
    try:
        server_pid = int(wait_for(lambda: log.read_text().strip(), timeout=60, what="its PID"))
        assert procs.alive(server_pid)
        client.kill()
        client.wait(timeout=30)
        deadline = time.monotonic() + 30
        while procs.alive(server_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not procs.alive(server_pid)
    finally:
        procs.end(client, 5)
