"""shared/net/roles.py and security.py without a network: the permission table as the ACL
enforces it (roles.py), the settings and their checks, where a router may listen, and
reading denials from zenoh's log (on lines a zenoh 1.10.2 router really wrote)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import zenoh

from shared.net import bus as keys
from shared.net.bus import session_config
from shared.net.roles import ROLES, acl_config, permissions_markdown, role_of
from shared.net.security import (
    AclLog,
    Denial,
    Security,
    SecurityError,
    check_router_listen,
    read_users_file,
)

ROOT = Path(__file__).resolve().parent.parent
USERS = ["actor0", "actor1", "counter", "learner", "evaluator", "api", "cli", "router", "router-b"]


def allowed(acl: dict, user: str, flow: str, message: str, key: str) -> bool:
    """What the router decides, as zenoh's ACL does: deny unless a rule of one of the
    user's policies, for this flow and message, has a key expression including `key`."""
    subjects = {s["id"] for s in acl["subjects"] if user in s.get("usernames", [])}
    rules = {r["id"]: r for r in acl["rules"]}
    for policy in acl["policies"]:
        if not subjects & set(policy["subjects"]):
            continue
        for rid in policy["rules"]:
            r = rules[rid]
            if flow in r["flows"] and message in r["messages"] and r["permission"] == "allow":
                ke = zenoh.KeyExpr(key)
                if any(zenoh.KeyExpr(k).includes(ke) for k in r["key_exprs"]):
                    return True
    return acl["default_permission"] == "allow"


ACL = acl_config(USERS)
RUN = "r1"


def test_only_the_api_and_the_cli_may_put_control():
    for user in USERS:
        may = allowed(ACL, user, "ingress", "put", keys.k_control("stop"))
        assert may == (user in ("api", "cli", "router", "router-b")), user
        assert allowed(ACL, user, "ingress", "put", keys.k_control("start")) == may, user


def test_an_actor_publishes_only_its_own_transitions_and_reads_weights_and_acks():
    put = lambda u, k: allowed(ACL, u, "ingress", "put", k)  # noqa: E731
    assert put("actor0", keys.k_transitions(RUN, "actor0"))
    assert not put("actor0", keys.k_transitions(RUN, "actor1"))
    assert put("actor1", keys.k_transitions(RUN, "actor1"))
    for key in (keys.k_weights(RUN, "latest"), keys.k_ack(RUN, "counter"), keys.k_bonus(RUN)):
        assert not put("actor0", key), key
    for key in (keys.k_weights("*", "*"), keys.k_ack("*", "*")):
        assert allowed(ACL, "actor0", "ingress", "declare_subscriber", key)
    assert allowed(ACL, "actor0", "egress", "put", keys.k_weights(RUN, "latest"))
    assert not allowed(ACL, "actor0", "ingress", "declare_subscriber", keys.k_transitions("*"))
    assert not allowed(ACL, "actor0", "ingress", "query", keys.k_bonus(RUN))


def test_the_learner_and_the_counter_do_their_part_only():
    assert allowed(ACL, "learner", "ingress", "put", keys.k_weights(RUN, "eval"))
    assert allowed(ACL, "learner", "ingress", "put", keys.k_ack(RUN, "learner"))
    assert allowed(ACL, "learner", "ingress", "query", keys.k_bonus(RUN))
    assert allowed(ACL, "learner", "egress", "reply", keys.k_bonus(RUN))
    assert not allowed(ACL, "learner", "ingress", "put", keys.k_ack(RUN, "counter"))
    assert not allowed(ACL, "learner", "ingress", "put", keys.k_transitions(RUN, "actor0"))
    assert allowed(ACL, "counter", "ingress", "declare_queryable", keys.k_bonus("*"))
    assert allowed(ACL, "counter", "egress", "query", keys.k_bonus(RUN))
    assert allowed(ACL, "counter", "ingress", "reply", keys.k_bonus(RUN))
    assert allowed(ACL, "counter", "ingress", "put", keys.k_ack(RUN, "counter"))
    assert not allowed(ACL, "counter", "ingress", "put", keys.k_weights(RUN, "latest"))
    assert not allowed(ACL, "evaluator", "ingress", "put", keys.k_weights(RUN, "eval"))
    assert allowed(ACL, "evaluator", "ingress", "put", keys.k_metrics(RUN, "eval"))
    # `macb ps` asks macb/info/*/*: the query as sent must reach every service's answer
    for user in ("actor0", "counter", "learner", "evaluator", "api"):
        assert allowed(ACL, user, "egress", "query", keys.k_info("*", "*")), user
    # an unknown user (none of the users file) gets nothing
    assert not allowed(ACL, "actor9", "ingress", "put", keys.k_transitions(RUN, "actor9"))


def test_routers_are_known_by_name_and_by_certificate():
    by_cert = {s["id"]: s for s in ACL["subjects"] if "cert_common_names" in s}
    assert set(by_cert) == {"cert.router", "cert.router-b"}
    assert by_cert["cert.router-b"]["cert_common_names"] == ["router-b"]
    # nobody else is known by certificate: a client's role is its user name
    assert all(len(p["subjects"]) == 1 for p in ACL["policies"] if "router" not in p["id"])


def test_zenoh_1_10_accepts_the_configs():
    sec = Security(tls_ca=Path("ca.pem"), tls_cert=Path("r.pem"), tls_key=Path("r.key"))
    conf = session_config("router", None, ["tls/127.0.0.1:7447"], None, ACL)
    conf.update(sec.zenoh_config("router"))
    zenoh.Config.from_json5(json.dumps(conf))  # raises on an unknown or mistyped field
    tls = conf["transport"]["link"]["tls"]
    assert tls["listen_certificate"] == "r.pem" and "enable_mtls" not in tls


@pytest.mark.parametrize(
    ("user", "role"),
    [("actor0", "actor"), ("actor-h2-0", "actor"), ("learner2", "learner"), ("router-b", "router")],
)
def test_a_user_name_says_its_role(user, role):
    assert role_of(user) == role


@pytest.mark.parametrize(
    "user", ["admin", "actorx", "Actor0", "", "-actor", "actor-**", "actor0/x", "actor-$*"]
)
def test_a_user_named_after_no_role_is_refused(user):
    with pytest.raises(SecurityError, match="names no role"):
        role_of(user)


def test_the_deploy_doc_shows_the_table_the_acl_enforces():
    doc = (ROOT / "docs" / "deploy.md").read_text()
    assert permissions_markdown() in doc
    assert set(ROLES) == {"actor", "learner", "counter", "evaluator", "api", "cli", "router"}


# ---------------------------------------------------------------- settings and files
def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.fixture
def folder(tmp_path):
    cert = "-----BEGIN CERTIFICATE-----\nMII\n-----END CERTIFICATE-----\n"
    key = "-----BEGIN PRIVATE KEY-----\nMII\n-----END PRIVATE KEY-----\n"
    for name in ("ca", "router", "actor0"):
        write(tmp_path / f"{name}.pem", cert)
    write(tmp_path / "router.key", key)
    write(tmp_path / "actor0.key", key)
    write(tmp_path / "actor0.password", "s3cret\n")
    write(tmp_path / "router.password", "r\n")
    write(tmp_path / "users.txt", "actor0:s3cret\nrouter:r\n")
    return tmp_path


def test_a_secrets_folder_fills_in_the_files(folder):
    sec = Security.from_env({"MACB_ZENOH_SECRETS": str(folder), "MACB_ZENOH_USER": "actor0"})
    assert sec.tls_ca == folder / "ca.pem" and sec.tls_cert == folder / "actor0.pem"
    assert sec.password_file == folder / "actor0.password" and sec.users_file is None
    sec.check("client")
    conf = sec.zenoh_config("client")
    assert conf["transport"]["auth"]["usrpwd"] == {"user": "actor0", "password": "s3cret"}
    assert "listen_certificate" not in conf["transport"]["link"]["tls"]
    router = Security.from_env({"MACB_ZENOH_SECRETS": str(folder), "MACB_ZENOH_USER": "router"})
    router = router.for_router()
    router.check("router")
    assert router.users_file == folder / "users.txt"
    assert {p["id"] for p in router.router_acl()["policies"]} == {"policy.actor0", "policy.router"}


def test_a_password_given_directly_wins_over_the_folders_file(folder):
    env = {"MACB_ZENOH_SECRETS": str(folder), "MACB_ZENOH_USER": "actor0"}
    sec = Security.from_env({**env, "MACB_ZENOH_PASSWORD": "other"})
    sec.check("client")
    assert sec.password_file is None and sec.password_value() == "other"


def test_no_settings_change_nothing():
    sec = Security.from_env({})
    assert not sec.configured
    assert session_config("client", ["tcp/127.0.0.1:7447"], None, sec) == {
        "mode": "client",
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "connect": {"endpoints": ["tcp/127.0.0.1:7447"]},
    }


@pytest.mark.parametrize(
    ("env", "mode", "match"),
    [
        ({"MACB_ZENOH_TLS_CA": "{d}/nope.pem"}, "client", "CA certificate {d}/nope.pem: no such"),
        ({"MACB_ZENOH_TLS_CA": "{d}/actor0.key"}, "client", "{d}/actor0.key: not a PEM cert"),
        ({"MACB_ZENOH_TLS_CA": "{d}"}, "client", "CA certificate {d}: cannot read it"),
        ({"MACB_ZENOH_PASSWORD": "x"}, "client", "no user"),
        ({"MACB_ZENOH_USER": "cli"}, "client", "user 'cli' has no password"),
        ({"MACB_ZENOH_USER": "boss", "MACB_ZENOH_PASSWORD": "x"}, "client", "names no role"),
        (
            {"MACB_ZENOH_TLS_CA": "{d}/ca.pem", "MACB_ZENOH_TLS_CERT": "{d}/ca.pem"},
            "client",
            "without its key",
        ),
        ({"MACB_ZENOH_TLS_CA": "{d}/ca.pem"}, "router", "a TLS router needs its certificate"),
        ({"MACB_ZENOH_TLS_CA": "{d}/ca.pem", "MACB_ZENOH_MTLS": "1"}, "client", "mTLS"),
        ({"MACB_ZENOH_MTLS": "maybe"}, "client", "want 1 or 0"),
        ({"MACB_ZENOH_USERS_FILE": "{d}/users.txt"}, "client", "for the router only"),
        ({"MACB_ZENOH_USERS_FILE": "{d}/bad.txt"}, "router", "bad.txt, line 2: want user:pass"),
        ({"MACB_ZENOH_USERS_FILE": "{d}/boss.txt"}, "router", "boss.txt, line 1: user 'boss'"),
        ({"MACB_ZENOH_SECRETS": "{d}/nowhere"}, "client", "no such directory"),
    ],
)
def test_bad_settings_are_refused_naming_the_file_or_variable(folder, env, mode, match):
    write(folder / "bad.txt", "cli:x\nlearner\n")
    write(folder / "boss.txt", "boss:x\n")
    env = {k: v.format(d=folder) for k, v in env.items()}
    with pytest.raises(SecurityError, match=match.format(d=folder).replace(".", r"\.")):
        Security.from_env(env).check(mode)


def test_the_users_file_is_zenohs_dictionary(tmp_path):
    f = write(tmp_path / "u.txt", "actor0:a:b\n\ncli:c\n")
    assert read_users_file(f) == {"actor0": "a:b", "cli": "c"}  # the password may hold ':'
    with pytest.raises(SecurityError, match="line 2: user 'cli' again"):
        read_users_file(write(tmp_path / "d.txt", "cli:a\ncli:b\n"))


# ---------------------------------------------------------------- where a router may listen
def test_a_router_on_loopback_needs_nothing():
    check_router_listen(["tcp/127.0.0.1:7447", "tcp/127.3.0.1:1", "tcp/[::1]:7447"], Security())
    check_router_listen(["tcp/localhost:7447"], Security())


def test_a_router_beyond_loopback_needs_tls_and_auth(folder):
    with pytest.raises(SecurityError) as err:
        check_router_listen(["tcp/0.0.0.0:7447"], Security())
    msg = str(err.value)
    assert "refusing to listen on tcp/0.0.0.0:7447" in msg
    assert "a tls/ endpoint" in msg and "TLS (" in msg and "authentication" in msg
    tls_only = Security(
        tls_ca=folder / "ca.pem", tls_cert=folder / "router.pem", tls_key=folder / "router.key"
    )
    with pytest.raises(SecurityError, match="authentication") as err:
        check_router_listen(["tls/10.0.0.5:7447"], tls_only)
    assert "TLS (" not in str(err.value)
    full = dataclasses.replace(tls_only, users_file=folder / "users.txt")
    check_router_listen(["tls/0.0.0.0:7447", "tls/[2001:db8::1]:7447"], full)
    with pytest.raises(SecurityError, match="tls/ endpoint"):
        check_router_listen(["tcp/0.0.0.0:7447"], full)


# ---------------------------------------------------------------- denials from zenoh's log
def zlog(thread: int, text: str) -> str:
    """A line as zenoh 1.10.2's logger writes it (colours included)."""
    return (
        "\x1b[2m2026-12-01T20:32:43.756430Z\x1b[0m \x1b[35mTRACE\x1b[0m rx-1 "
        f"ThreadId({thread:02d}) \x1b[2mzenoh::net::routing::interceptor::access_control"
        "\x1b[0m\x1b[2m:\x1b[0m " + text + "\n"
    )


ZID = "dca235c2eabc598cb56445cd6178a0ae"
SUBJ = f"{ZID} on Interface(lo)+Username(actor0)+Transport(Tls)+{ZID}"
KINDS = [
    "Query",
    "Reply",
    "Put",
    "Delete",
    "Declare/Undeclare Subscriber",
    "Declare/Undeclare Queryable",
    "Declare/Undeclare Liveliness Token",
    "Liveliness Query",
    "Declare Liveliness Subscriber",
]


def test_cached_verdicts_are_not_denials_but_messages_dropped_are():
    log = AclLog()
    key = "macb/control/stop"
    block = [zlog(9, f"ACL (ingress): caching permissions for `{key}` ...")]
    block += [zlog(9, f"{SUBJ} is unauthorized to {k} (ingress) on {key}") for k in KINDS]
    # another thread's message checked while the block is written
    other = zlog(8, f"{SUBJ} is unauthorized to Put (ingress) on macb/run/r/transitions/actor1")
    got = [log.feed(line) for line in block[:4]]
    got.append(log.feed(other))
    got += [log.feed(line) for line in block[4:]]
    assert (
        got
        == [None] * 4
        + [Denial("actor0", "Put", "ingress", "macb/run/r/transitions/actor1")]
        + [None] * 6
    )
    cached = zlog(9, f"Using cached result: {ZID} is unauthorized to Put (ingress) on {key}")
    assert log.feed(cached) == Denial("actor0", "Put", "ingress", key)  # user learnt above
    allowed_line = zlog(9, f"Using cached result: {ZID} is authorized to Put (ingress) on {key}")
    assert log.feed(allowed_line) is None
    assert log.feed(zlog(9, f"{SUBJ} is authorized to Put (ingress) on x")) is None
    assert log.feed("some other zenoh line\n") is None
    unknown = zlog(3, "Using cached result: 00ff is unauthorized to Query (egress) on a/b")
    assert log.feed(unknown) == Denial("00ff", "Query", "egress", "a/b")


def test_with_tls_a_plain_tcp_endpoint_off_loopback_is_refused(folder):
    sec = Security.from_env({"MACB_ZENOH_SECRETS": str(folder), "MACB_ZENOH_USER": "actor0"})
    with pytest.raises(SecurityError, match="use tls/10.0.0.5:7447"):
        session_config("client", ["tcp/10.0.0.5:7447"], None, sec)
    session_config("client", ["tls/10.0.0.5:7447", "tcp/127.0.0.1:7447"], None, sec)
