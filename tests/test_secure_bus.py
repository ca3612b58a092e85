"""The secure bus on real processes over 127.0.0.1: TLS, user/password, the router's ACL.

Certificates and credentials are made per test module by `macb certs` (openssl) in a
tmp dir. What could fail here: a session without or with wrong credentials getting in,
a certificate of another CA accepted, the ACL letting an actor stop a run (or the ACL
denying something a normal run needs: a normal run must see no denial at all), a
router listening off loopback without TLS and auth, a bad file half-starting a service.
"""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest

from shared.config import make_config
from shared.net import bus as keys
from shared.net.bus import Bus
from shared.net.control import send_stop, start_run
from shared.net.messages import Stop
from shared.net.security import Security
from shared.net.wire import encode
from tests.harness import (
    SMALL,
    TINY,
    Cluster,
    as_user,
    assert_exact,
    free_port,
    macb,
    router_stats,
    session,
    wait_final_counts,
    wait_for,
    wait_services,
    write_config,
)

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")


@pytest.fixture
def secure(secrets, tmp_path):
    """A TLS router with user/password and the ACL on its own loopback port."""
    with Cluster(tmp_path, secrets=secrets) as cluster:
        cluster.router()
        yield cluster


def test_secure_lockstep_run_is_exact_with_no_denial(secure, secrets):
    """`interleave: lockstep` over TLS: the actor's act requests and the learner's
    actions are keys the ACL grants (docs/deploy.md's table), so the run completes
    exactly and the router denies nothing."""
    secure.services(actors=1)
    config = make_config({**SMALL, "episodes": 10, "interleave": "lockstep"})
    with session(secrets, "cli", secure.endpoint) as cli:
        wait_services(cli, 4)
        watch = start_run(cli, config, actors=1)
        assert watch.wait(timeout=240) == "completed", watch.states
        learner = assert_exact(watch, config).learner
        assert learner["policy_lag"] == 0.0
        stats = router_stats(cli)
    assert stats["denied"] == [], stats


def test_secure_run_is_exact_and_an_actor_cannot_stop_it(secure, secrets):
    """A whole run over TLS with every service signed in: exact counts, ratio 1, and no
    denial at all (the ACL grants what a run needs). Meanwhile an actor's credentials
    try to stop the run and to publish another actor's transitions: both denied, logged
    and counted by the router, and the run completes."""
    secure.services(actors=1)
    config = make_config({**SMALL, "episodes": 30})
    with session(secrets, "cli", secure.endpoint) as cli:
        wait_services(cli, 4)
        watch = start_run(cli, config, actors=1)
        with session(secrets, "actor0", secure.endpoint) as rogue:
            wait_for(lambda: watch.rows, timeout=60, what="a first point")
            send_stop(rogue, watch.run, "forged")
            rogue.put(keys.k_transitions(watch.run, "actor1"), encode(Stop(watch.run, reason="x")))
            # Both at the router before the session closes (a close can drop what is
            # still queued; a fixed sleep was the guess of how long that takes).
            wait_for(lambda: router_stats(cli)["denied_total"] >= 2, timeout=30, what="the denials")
        assert watch.wait(timeout=240) == "completed", watch.states
        wait_final_counts(watch, config)
        assert_exact(watch, config)
        stats = router_stats(cli)
    denied = {(d["user"], d["what"], d["key"]): d["count"] for d in stats["denied"]}
    assert denied == {
        ("actor0", "Put", keys.k_control("stop")): 1,
        ("actor0", "Put", keys.k_transitions(watch.run, "actor1")): 1,
    }, stats
    log = secure.log("router")
    assert f"ACL denied: user actor0 (actor) Put (ingress) on {keys.k_control('stop')}" in log
    ps = macb("ps", "--connect", secure.endpoint, env=as_user(secrets, "cli"))
    assert ps.returncode == 0 and "acl denied=2" in ps.stdout, ps.stdout + ps.stderr


def test_macb_certs_makes_a_ca_and_certificates_it_alone_signed(secrets, other_ca, tmp_path):
    def verify(ca: Path, cert: Path) -> bool:
        r = subprocess.run(["openssl", "verify", "-CAfile", ca, cert], capture_output=True)
        return r.returncode == 0

    assert verify(secrets / "ca.pem", secrets / "router-b.pem")
    assert verify(secrets / "ca.pem", secrets / "actor1.pem")
    assert not verify(other_ca / "ca.pem", secrets / "router.pem")
    text = subprocess.run(
        ["openssl", "x509", "-in", secrets / "router-b.pem", "-noout", "-text"],
        capture_output=True,
        text=True,
    ).stdout
    assert "DNS:localhost" in text and "IP Address:127.0.0.1" in text and "DNS:router-b" in text
    users = dict(line.split(":", 1) for line in (secrets / "users.txt").read_text().split())
    assert set(users) >= {"counter", "learner", "evaluator", "api", "cli", "actor0", "router-b"}
    assert users["actor0"] == (secrets / "actor0.password").read_text().strip()
    assert (secrets / "ca.key").stat().st_mode & 0o077 == 0
    # again, with one more user: the others are kept as they were
    out = tmp_path / "s"
    shutil.copytree(secrets, out)
    before = (out / "users.txt").read_text()
    r = macb("certs", str(out), "--user", "actor-h2-0")
    assert r.returncode == 0, r.stderr
    assert (out / "users.txt").read_text().startswith(before)
    assert "actor-h2-0:" in (out / "users.txt").read_text()
    assert verify(out / "ca.pem", out / "actor-h2-0.pem")
    r = macb("certs", str(out), "--user", "boss")
    assert r.returncode == 2 and "names no role" in r.stderr


def test_macb_certs_again_with_router_hosts_re_signs_that_router_s_certificate(tmp_path):
    """docs/deploy.md's way from one node to several: `macb certs DIR`, later `macb certs
    DIR --router router=cn01,cn02`. The router's certificate must then pass the TLS host
    check for cn01 and cn02 (it was once kept as it was, exit 0), signed by the same CA for
    the same key; asking again for names it has changes nothing."""

    def host_ok(cert: Path, host: str) -> bool:
        argv = ["openssl", "verify", "-CAfile", out / "ca.pem", "-verify_hostname", host, cert]
        return subprocess.run(argv, capture_output=True).returncode == 0

    def pubkey(*argv: object) -> str:
        return subprocess.run(["openssl", *map(str, argv)], capture_output=True, text=True).stdout

    out = tmp_path / "secrets"
    macb("certs", str(out), check=True)
    router, key = out / "router.pem", out / "router.key"
    key_before, actor_before = key.read_bytes(), (out / "actor0.pem").read_bytes()
    assert host_ok(router, "router") and not host_ok(router, "cn01")
    r = macb("certs", str(out), "--router", "router=cn01,cn02,10.0.0.7,::1", check=True)
    added = "DNS:cn01, DNS:cn02, IP:10.0.0.7, IP:::1"
    assert f"router.pem: re-signed to add {added}, its key kept" in r.stdout, r.stdout
    for host in ("cn01", "cn02", "router", "localhost"):
        assert host_ok(router, host), host
    text = subprocess.run(
        ["openssl", "x509", "-in", router, "-noout", "-ext", "subjectAltName"],
        capture_output=True, text=True,
    ).stdout  # fmt: skip
    assert "IP Address:10.0.0.7" in text and "IP Address:127.0.0.1" in text, text
    assert "IP Address:0:0:0:0:0:0:0:1" in text, text
    assert key.read_bytes() == key_before
    assert pubkey("x509", "-in", router, "-noout", "-pubkey") == pubkey(
        "pkey", "-in", key, "-pubout"
    )
    assert (out / "actor0.pem").read_bytes() == actor_before  # the others as they were
    # names it already carries (in any case, an IP in any form): nothing to do
    signed = router.read_bytes()
    r = macb("certs", str(out), "--router", "router=CN01,0:0::1", check=True)
    assert "re-signed" not in r.stdout and router.read_bytes() == signed
    # a certificate to re-sign without its key: refused, naming both
    key.unlink()
    r = macb("certs", str(out), "--router", "router=cn03")
    assert r.returncode == 2 and f"its key {key} is missing" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and router.read_bytes() == signed


@pytest.mark.parametrize(
    "case", ["no credentials", "wrong password", "unknown user", "no TLS", "another CA"]
)
def test_a_client_that_cannot_prove_itself_is_refused(secure, secrets, other_ca, tmp_path, case):
    bad = tmp_path / "bad.password"
    bad.write_text("not-the-password\n")
    port = secure.endpoint.rsplit(":", 1)[1]
    endpoint, sec = secure.endpoint, None
    if case == "no credentials":
        sec = Security(tls_ca=secrets / "ca.pem")
    elif case == "wrong password":
        sec = Security(user="cli", password_file=bad, tls_ca=secrets / "ca.pem")
    elif case == "unknown user":
        sec = Security(user="actor7", password_file=bad, tls_ca=secrets / "ca.pem")
    elif case == "no TLS":
        endpoint = f"tcp/127.0.0.1:{port}"
        sec = Security(user="cli", password_file=secrets / "cli.password")
    else:  # the client trusts another CA: the router's certificate is not one of its
        sec = Security(
            user="cli", password_file=secrets / "cli.password", tls_ca=other_ca / "ca.pem"
        )
    with pytest.raises(Exception, match="Unable to connect"):
        Bus([endpoint], security=sec).close()
    # the right credentials still get in
    with session(secrets, "cli", secure.endpoint) as ok:
        assert router_stats(ok)["acl"] is True


def test_mtls_refuses_a_certificate_from_another_ca(secrets, other_ca, tmp_path):
    mtls = {"MACB_ZENOH_MTLS": "1"}
    with Cluster(tmp_path, secrets=secrets, env=mtls) as cluster:
        endpoint = cluster.router()
        foreign = {
            **mtls,
            "MACB_ZENOH_TLS_CERT": str(other_ca / "cli.pem"),
            "MACB_ZENOH_TLS_KEY": str(other_ca / "cli.key"),
        }
        with pytest.raises(Exception, match="Unable to connect"):
            session(secrets, "cli", endpoint, **foreign).close()
        with session(secrets, "cli", endpoint, **mtls) as ok:
            assert router_stats(ok)["acl"] is True


def test_router_off_loopback_refuses_to_start_without_tls_and_auth(secrets, tmp_path):
    port = free_port()
    r = macb("serve", "router", "--listen", f"tcp/0.0.0.0:{port}", timeout=30)
    assert r.returncode == 2, r.stderr
    assert f"refusing to listen on tcp/0.0.0.0:{port}" in r.stderr
    assert "TLS" in r.stderr and "authentication" in r.stderr
    # TLS alone is not enough: authentication (the users file) is missing
    env = {
        "MACB_ZENOH_TLS_CA": str(secrets / "ca.pem"),
        "MACB_ZENOH_TLS_CERT": str(secrets / "router.pem"),
        "MACB_ZENOH_TLS_KEY": str(secrets / "router.key"),
    }
    r = macb("serve", "router", "--listen", f"tls/10.255.255.1:{port}", env=env, timeout=30)
    assert r.returncode == 2 and "authentication" in r.stderr and "TLS (" not in r.stderr, r.stderr


@pytest.mark.parametrize("role", ["router", "counter", "api"])
def test_a_missing_or_unreadable_file_is_refused_at_start_naming_it(secrets, tmp_path, role):
    missing = tmp_path / "nope" / "ca.pem"
    env = {**as_user(secrets, role if role != "api" else "api"), "MACB_ZENOH_TLS_CA": str(missing)}
    args = ["serve", role, "--data-dir", str(tmp_path / "d")]
    if role == "router":
        args += ["--listen", f"tls/127.0.0.1:{free_port()}"]
    t0 = time.monotonic()
    r = macb(*args, env=env, timeout=30)
    assert r.returncode == 2, r.stderr
    assert f"CA certificate {missing}: no such file" in r.stderr
    assert time.monotonic() - t0 < 20
    assert not (tmp_path / "d").exists(), "nothing half-started"
    # a directory where the password file should be: unreadable, named
    env = {**as_user(secrets, "counter"), "MACB_ZENOH_PASSWORD_FILE": str(tmp_path)}
    r = macb("serve", "counter", env=env, timeout=30)
    assert r.returncode == 2 and f"password file {tmp_path}: cannot read it" in r.stderr


def test_macb_up_with_secrets_runs_the_secure_bus_end_to_end(secrets, tmp_path):
    """`macb up --secrets DIR --run`: TLS on loopback, every service (and the API, and
    `macb up` itself as cli) signed in as its own user, the ACL on, nothing denied."""
    cfg = write_config(tmp_path / "tiny.yaml", TINY)
    out_dir = tmp_path / "out"
    run = ("--run", str(cfg), "--out", str(out_dir))
    with Cluster(tmp_path) as cluster:  # a tcp/ endpoint: --secrets makes it TLS
        cluster.up("--quiet", "--secrets", str(secrets), *run)
        code, out = cluster.wait(timeout=240)
        assert code == 0, out
        assert "completed" in out
        rows = (out_dir / "metrics.csv").read_text().splitlines()
        assert len(rows) == 1 + 3
        log = (tmp_path / "data" / "logs" / "router.log").read_text()
        assert f"listening on tls/{cluster.endpoint.split('/', 1)[1]}" in log, log
        assert "TLS, user/password, ACL for" in log and "ACL denied" not in log, log
        assert cluster.leftovers() == []


def test_macb_up_refuses_a_secrets_folder_without_a_services_files(secrets, tmp_path):
    """The folder has actor0 and actor1: a third actor's missing password is named, exit
    2, before any process starts."""
    args = ["up", "--secrets", str(secrets), "--actors", "3", "--no-api"]
    r = macb(*args, "--data-dir", str(tmp_path / "d"), "--endpoint", f"tcp/127.0.0.1:{free_port()}")
    assert r.returncode == 2, r.stdout + r.stderr
    assert "user 'actor2' has no password" in r.stderr and "actor2.password" in r.stderr
    assert not (tmp_path / "d").exists()
