"""A bus session that cannot open (shared/net/bus.py, `Bus`): no router at the endpoint,
or the port a router would listen on taken. `macb` says so in one line naming the
endpoint and zenoh's reason, exit 2, as for any bad input (it was a traceback ending in
`zenoh.ZError`). Real sessions on real 127.0.0.1 ports."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from shared.net.bus import Bus
from shared.net.security import BusError, Security
from tests.harness import free_port, macb


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A port on 127.0.0.1 that this process listens on for the test."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def one_line_error(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert "Traceback" not in stderr and len(lines) == 1, stderr
    return lines[0]


def test_macb_ps_with_no_router_at_the_endpoint_says_so():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    r = macb("ps", "--connect", endpoint, timeout=60)
    assert r.returncode == 2, r.stderr
    line = one_line_error(r.stderr)
    assert line.startswith(
        f"macb ps: cannot open a client session on the bus (connecting to {endpoint})"
    )
    assert "Unable to connect" in line and ".rs:" not in line, line


def test_a_router_on_a_port_in_use_says_so(taken_port):
    endpoint = f"tcp/127.0.0.1:{taken_port}"
    r = macb("serve", "router", "--listen", endpoint, timeout=60)
    assert r.returncode == 2, r.stderr
    line = one_line_error(r.stderr)
    assert line.startswith(
        f"macb serve router: cannot open a router session on the bus (listening on {endpoint})"
    )
    assert "Address already in use" in line and ".rs:" not in line, line


def test_a_service_with_no_router_says_so_and_makes_nothing(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    data = tmp_path / "counter"
    r = macb("serve", "counter", "--connect", endpoint, "--data-dir", str(data), timeout=60)
    assert r.returncode == 2, r.stderr
    line = one_line_error(r.stderr)
    assert line.startswith(
        f"macb serve counter: cannot open a client session on the bus (connecting to {endpoint})"
    )
    assert not data.exists()


def test_bus_raises_bus_error_naming_every_endpoint(taken_port):
    """In process too: the API's scheduler and the tests catch it (any Exception)."""
    free = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(BusError, match=r"connecting to .*: Unable to connect"):
        Bus([free], security=Security())
    taken = f"tcp/127.0.0.1:{taken_port}"
    with pytest.raises(BusError, match=rf"router session .*listening on {taken}\): .*in use"):
        Bus.router([taken], security=Security())
