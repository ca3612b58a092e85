"""Fixtures for tests with a real Zenoh router and real service processes on loopback."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import httpx
import pytest

from tests.harness import (  # noqa: F401 (tests import ROOT, wait_for and the ports from here)
    ROOT,
    Cluster,
    free_port,
    macb,
    start_api,
    wait_for,
    wait_port,
)


def _load_offline():
    """docker/offline.py (the image built without a registry): a stdlib-only script,
    not a package, so it is loaded from its path."""
    spec = importlib.util.spec_from_file_location("macb_offline", ROOT / "docker" / "offline.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


offline = _load_offline()


def _certs(out, *args: str):
    r = macb("certs", str(out), *args, timeout=60)
    assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="session")
def secrets(tmp_path_factory) -> Path:
    """A cluster's CA, certificates and credentials, made by `macb certs` (openssl):
    routers `router` and `router-b`, actors actor0 and actor1, the other roles."""
    if shutil.which("openssl") is None:
        pytest.skip("macb certs needs the openssl command")
    out = tmp_path_factory.mktemp("secrets")
    return _certs(out, "--router", "router", "--router", "router-b", "--actors", "2")


@pytest.fixture(scope="session")
def other_ca(tmp_path_factory) -> Path:
    """Another CA with the same names: its certificates must be refused."""
    if shutil.which("openssl") is None:
        pytest.skip("macb certs needs the openssl command")
    return _certs(tmp_path_factory.mktemp("other-ca"), "--actors", "1")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Keep each phase's report on the test item, so fixtures can see a failure."""
    outcome = yield
    report = outcome.get_result()
    setattr(item, f"rep_{report.when}", report)


@pytest.fixture
def cluster(tmp_path, request):
    """A router on a loopback port of its own; the test starts the services it needs
    (`cluster.services(...)`). Every process is ended by PID after the test, and when
    the test failed the end of each one's log is in its report."""
    with Cluster(tmp_path) as c:
        c.router()
        yield c
        failed = getattr(request.node, "rep_call", None)
        if failed is not None and failed.failed:  # the services' own account
            c.report()


@pytest.fixture
def router(cluster) -> str:
    """A real router process on its own loopback port: its endpoint."""
    return cluster.endpoint


@pytest.fixture
def bus(router):
    from shared.net.bus import Bus

    b = Bus([router])
    yield b
    b.close()


@pytest.fixture
def api(router, tmp_path):
    """The API in this process on a real router and a store of its own."""
    server = start_api(tmp_path, router)
    yield server
    server.stop()


@pytest.fixture
def client(api):
    with httpx.Client(base_url=api.url, timeout=20) as c:
        yield c
