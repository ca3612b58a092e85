"""A cluster's ports and readiness (cli/supervisor.py, services/api/client.py): a port
someone else listens on is refused before anything starts, naming it, and an answer on a
port or on /health counts only while our own process lives. Otherwise, with 7447 or 8000
taken (another `macb up`, compose, another user's job), our router and API fail to bind,
every check passes against the other listener, and the services join that cluster."""

from __future__ import annotations

import socket
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from cli.supervisor import (
    DidNotListen,
    PortInUse,
    check_port_free,
    check_ports,
    cluster_plan,
    free_port,
    wait_port,
)
from shared import procs


@contextmanager
def listening(port: int) -> Iterator[socket.socket]:
    """A plain socket listening on 127.0.0.1:port: anyone's process."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
        s.listen()
        yield s


def test_a_port_someone_listens_on_is_refused_naming_it_and_a_free_one_passes():
    port = free_port()
    check_port_free("127.0.0.1", port)
    taken = f"port {port} on 127.0.0.1 is in use: something listens on it"
    with listening(port), pytest.raises(PortInUse, match=taken):
        check_port_free("127.0.0.1", port)
    check_port_free("127.0.0.1", port)  # closed: free again


def test_the_plan_names_each_taken_port_and_whose_it_would_be():
    router, api = free_port(), free_port()
    plan = cluster_plan(endpoint=f"tcp/127.0.0.1:{router}", api=f"127.0.0.1:{api}")
    check_ports(plan)
    with listening(router), listening(api), pytest.raises(PortInUse) as got:
        check_ports(plan)
    why = str(got.value)
    assert f"router: port {router} on 127.0.0.1" in why and f"api: port {api} on " in why, why


def test_a_port_that_answers_for_a_child_that_ended_is_not_the_childs():
    """The child that was to listen has ended (its bind failed): the port answering,
    for someone else, does not count."""
    port = free_port()
    child = procs.start([sys.executable, "-c", "pass"])
    child.wait(timeout=30)
    with listening(port), pytest.raises(DidNotListen, match="ended"):
        wait_port(f"tcp/127.0.0.1:{port}", timeout=5, proc=child)


def test_a_healthy_answer_counts_only_while_our_api_process_lives(monkeypatch):
    from services.api.client import ApiClient

    monkeypatch.setattr(ApiClient, "health", lambda self: {"bus": True})  # someone's API
    with ApiClient(f"http://127.0.0.1:{free_port()}") as api:
        with pytest.raises(TimeoutError, match="a process ended"):
            api.wait_healthy(5, alive=lambda: False)
        api.wait_healthy(5, alive=lambda: True)
