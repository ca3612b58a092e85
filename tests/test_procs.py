"""shared/procs.py, the one way children are started and ended by PID (`macb up`'s
supervisor, tests/harness.py, benchmarks/_procs.py): each child in a session of its
own, SIGTERM first, SIGKILL (to it, or its whole group) once its grace is over."""

from __future__ import annotations

import os
import signal
import socket
import sys
import time
from pathlib import Path

from cli.supervisor import _ephemeral_range, free_port
from shared import procs

# A child that ignores SIGTERM and starts a grandchild in its group (which would be
# left behind by a kill of the child alone), printing the grandchild's PID.
STUBBORN = """
import os, signal, subprocess, sys, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)
g = subprocess.Popen([sys.executable, "-c", "import signal, time; "
    "signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(60)"])
print(g.pid, flush=True)
time.sleep(60)
"""


def grandchild(log: Path) -> int:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        text = log.read_text().strip()
        if text:
            return int(text)
        time.sleep(0.05)
    raise TimeoutError("the child did not start its grandchild")


def test_a_child_runs_in_a_session_of_its_own_and_logs_to_its_file(tmp_path):
    log = tmp_path / "child.log"
    p = procs.start([sys.executable, "-c", "import os; print(os.getsid(0))"], log=log)
    assert p.wait(timeout=30) == 0
    assert int(log.read_text()) == p.pid != os.getsid(0)  # its own session, led by it
    piped = procs.start([sys.executable, "-c", "print('hi')"], pipe=True)
    assert piped.stdout is not None and piped.stdout.read() == b"hi\n"
    piped.wait(timeout=30)


def test_end_asks_first_and_a_child_that_exits_is_not_killed(tmp_path):
    p = procs.start([sys.executable, "-c", "import time; time.sleep(60)"])
    procs.end(p, grace=30)
    assert p.returncode == -signal.SIGTERM  # SIGTERM was enough
    procs.end(p, grace=30)  # ended already: nothing to do


def test_past_its_grace_a_child_is_killed_by_pid_or_with_its_whole_group(tmp_path):
    for group in (False, True):
        log = tmp_path / f"stubborn-{group}.log"
        p = procs.start([sys.executable, "-c", STUBBORN], log=log)
        g = grandchild(log)
        assert procs.alive(g) and procs.names_one_of(g, ("time.sleep(60)",))
        procs.end_all([p], grace=0.2, group=group)
        assert p.returncode == -signal.SIGKILL
        if group:  # a group kill takes the grandchild too (it dies once it is scheduled)
            _gone(g)
        else:
            time.sleep(0.2)
            assert procs.alive(g)  # left behind by a kill of the child alone
            procs.send(g, signal.SIGKILL)  # ours: end it here (by PID)
            _gone(g)


def _gone(pid: int) -> None:
    """Until `pid` has ended: a process SIGKILLed ends when it next runs, which on a
    loaded machine can be later than a fixed sleep."""
    deadline = time.monotonic() + 10
    while procs.alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not procs.alive(pid)


def test_a_child_that_exited_is_not_alive_and_signalling_it_is_no_error():
    p = procs.start([sys.executable, "-c", "pass"])
    deadline = time.monotonic() + 30
    while procs.alive(p.pid) and time.monotonic() < deadline:  # exited, not reaped yet
        time.sleep(0.05)
    assert not procs.alive(p.pid)
    procs.send(p.pid, signal.SIGTERM)  # still our (zombie) child: its PID is not reused
    assert p.wait(timeout=30) == 0


def test_free_port_hands_out_ports_outgoing_connections_do_not_take_each_once():
    """A free port is released before its process binds it: drawn below the kernel's
    ephemeral range, an outgoing connection cannot take it meanwhile, and one process
    never gets the same port twice."""
    first, _ = _ephemeral_range()
    ports = [free_port() for _ in range(50)]
    assert len(set(ports)) == 50 and all(20000 <= p < first for p in ports)
    with socket.socket() as s:
        s.bind(("127.0.0.1", ports[-1]))  # it is free
        s.listen()
        assert free_port() != ports[-1]


def test_a_child_given_its_parents_pid_dies_with_it_and_passes_the_pid_on_to_none():
    """MACB_PARENT_PID (what `macb up`'s supervisor gives each service): the child arms
    its death with that process and takes the variable out of its environment, so a
    process it starts does not take that PID for its parent's (and kill itself); a value
    that is not a PID is refused, `macb` exiting 2 naming it."""
    from tests.harness import ROOT, macb

    code = (
        "import os; from shared import procs; "
        "print(procs.die_with_env_parent(), os.environ.get(procs.PARENT_ENV))"
    )
    env = {**os.environ, **procs.parent_env()}
    child = procs.start([sys.executable, "-c", code], pipe=True, env=env, cwd=ROOT)
    out, _ = child.communicate(timeout=60)
    assert out.decode().split() == ["prctl", "None"], out
    got = macb("ps", env={procs.PARENT_ENV: "abc"}, timeout=120)
    assert got.returncode == 2, got.stderr[-2000:]
    assert "MACB_PARENT_PID must be a process id, not 'abc'" in got.stderr
