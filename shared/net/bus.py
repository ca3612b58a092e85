"""The Zenoh layer: sessions, the key space, publishers, subscribers, queries, liveliness.

This is the only module that imports zenoh. Services connect as clients to one
router (a Python session in router mode: no separate binary). Multicast scouting is
off: endpoints are explicit, loopback by default, and set per host for multi-host
clusters (`MACB_ZENOH_CONNECT=tls/10.0.0.5:7447`). Security (TLS, user/password, the
router's ACL) is built by `shared.net.security` from `MACB_ZENOH_*` variables; with none
set, sessions are plain TCP without credentials, as on one machine.

Callbacks run on Zenoh's threads; the wrappers here hand raw bytes to the caller's
callback, which should only enqueue (see services/common.py).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from shared.net.security import BusError, Security, check_endpoints_match
from shared.settings import settings

log = logging.getLogger("macb.bus")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
NS = "macb"


# ---------------------------------------------------------------- the key space
def k_transitions(run: str, actor: str = "*") -> str:
    return f"{NS}/run/{run}/transitions/{actor}"


def k_ack(run: str, service: str = "*") -> str:
    return f"{NS}/run/{run}/ack/{service}"


def k_weights(run: str, kind: str = "*") -> str:
    """kind "latest": every boundary; "eval": boundaries marked as evaluation points."""
    return f"{NS}/run/{run}/weights/{kind}"


def k_act(run: str, actor: str = "*") -> str:
    """Lockstep: an actor's requests for the policy's action at its next step."""
    return f"{NS}/run/{run}/act/{actor}"


def k_action(run: str, actor: str = "*") -> str:
    """Lockstep: the learner's answers to one actor's act requests."""
    return f"{NS}/run/{run}/action/{actor}"


def k_bonus(run: str) -> str:
    return f"{NS}/run/{run}/bonus"


def k_metrics(run: str, source: str = "**") -> str:
    return f"{NS}/run/{run}/metrics/{source}"


def k_history(run: str, source: str = "eval") -> str:
    """Queryable: every metric row `source` has published for the run (gap filling)."""
    return f"{NS}/run/{run}/history/{source}"


def k_status(run: str, service: str = "*") -> str:
    return f"{NS}/run/{run}/status/{service}"


def k_control(action: str) -> str:
    return f"{NS}/control/{action}"


def k_live(role: str = "*", service: str = "*") -> str:
    return f"{NS}/live/{role}/{service}"


def k_info(role: str = "*", service: str = "*") -> str:
    return f"{NS}/info/{role}/{service}"


def k_router(router: str = "*") -> str:
    """Queryable of each router: its ACL's denial counts (JSON)."""
    return f"{NS}/router/{router}"


def run_of(key: str) -> str | None:
    """The run id inside a per-run key, or None."""
    parts = key.split("/")
    return parts[2] if len(parts) > 2 and parts[0] == NS and parts[1] == "run" else None


# ---------------------------------------------------------------- sessions
def default_connect() -> list[str]:
    raw = settings().zenoh_connect
    raw = DEFAULT_ENDPOINT if raw is None else raw
    return [e.strip() for e in raw.split(",") if e.strip()]


def session_config(
    mode: str,
    connect: list[str] | None,
    listen: list[str] | None,
    security: Security | None = None,
    acl: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The session's Zenoh config as a dict (security checked first: SecurityError)."""
    conf: dict[str, Any] = {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    if connect:
        conf["connect"] = {"endpoints": connect}
    if listen:
        conf["listen"] = {"endpoints": listen}
    if security is not None and security.configured:
        security.check(mode)
        check_endpoints_match(connect or [], security)
        conf.update(security.zenoh_config(mode))
    if acl is not None:
        conf["access_control"] = acl
    return conf


def _config(
    mode: str,
    connect: list[str] | None,
    listen: list[str] | None,
    security: Security | None = None,
    acl: dict[str, Any] | None = None,
) -> zenoh.Config:
    conf = json.dumps(session_config(mode, connect, listen, security, acl))
    try:
        return zenoh.Config.from_json5(conf)
    except zenoh.ZError as err:  # an endpoint not of the form proto/address, say
        where = ", ".join([*(connect or []), *(listen or [])]) or "the defaults"
        why = str(err).split(" at /", 1)[0]  # (without the Rust source location)
        raise BusError(f"bus endpoints {where}: {why}") from None


_logging_ready = False


def _init_logging() -> None:
    global _logging_ready
    if not _logging_ready:
        zenoh.init_log_from_env_or("error")
        _logging_ready = True


def capture_zenoh_log(target: str, on_line: Callable[[str], None]) -> None:
    """Turn on TRACE for one zenoh log target and hand its lines to `on_line`.

    Zenoh's Rust logger writes to this process's stdout (fd 1), so fd 1 becomes a pipe
    read by a thread here: lines of `target` go to `on_line`, every other line to the
    real stdout. Call before the first session opens (the log level is set once per
    process). The router uses it to count its ACL's denials, which zenoh only logs."""
    global _logging_ready
    if _logging_ready:
        raise RuntimeError("capture_zenoh_log must come before the first session")
    base = os.environ.get("RUST_LOG", "error")
    os.environ["RUST_LOG"] = f"{base},{target}=trace"
    real_stdout = os.dup(1)
    r, w = os.pipe()
    os.dup2(w, 1)
    os.close(w)

    def pump() -> None:
        with os.fdopen(r, "rb", buffering=1 << 16) as pipe:
            for raw in pipe:
                if target.encode() in raw:
                    try:
                        on_line(raw.decode(errors="replace"))
                    except Exception:  # a bad line must not stop the pump (zenoh would block)
                        log.exception("zenoh log line handler failed")
                else:
                    os.write(real_stdout, raw)

    threading.Thread(target=pump, name="zenoh-log", daemon=True).start()
    _init_logging()


REFUSED = b"refused: "  # an error reply of ours; Zenoh's own ("Timeout") lack it


@dataclass(frozen=True)
class Refused:
    """A query handler's refusal: sent as an error reply `refused: <by>: <reason>`, so
    the asker tells a refused query from one nobody answered in time (Zenoh ends a query
    that timed out with an error reply of its own, which is not a refusal), and whose
    refusal it is (several services may answer one key: a counter per node)."""

    by: str
    reason: str

    def payload(self) -> bytes:
        return REFUSED + f"{self.by}: {self.reason}".encode()

    @classmethod
    def read(cls, raw: bytes) -> Refused | None:
        """The refusal an error reply carries; None for any other error reply."""
        if not raw.startswith(REFUSED):
            return None
        by, _, reason = raw[len(REFUSED) :].decode(errors="replace").partition(": ")
        return cls(by, reason)


@dataclass
class Replies:
    """A query's replies: each ok reply's payload, and each refusal."""

    ok: list[bytes] = field(default_factory=list)
    refused: list[Refused] = field(default_factory=list)


def open_failure(
    mode: str, connect: list[str] | None, listen: list[str] | None, err: Exception
) -> str:
    """Why a session did not open, in one line: its endpoints and zenoh's reason without
    the Rust source locations zenoh appends (" at .../orchestrator.rs:447.")."""
    where = []
    if connect:
        where.append(f"connecting to {', '.join(connect)}")
    if listen:
        where.append(f"listening on {', '.join(listen)}")
    reason = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(err)).strip()
    return f"cannot open a {mode} session on the bus ({'; '.join(where)}): {reason}"


class Publisher:
    """A publisher a `Bus` declared: called with a payload, it puts it. Each holds
    state in the session until it is undeclared, so a long-lived service undeclares
    the ones of a run when it lets the run go (`Endpoint.drop_run`), not only when its
    session closes."""

    def __init__(self, bus: Bus, pub: Any) -> None:
        self._bus, self._pub = bus, pub
        self.put = pub.put

    def __call__(self, payload: bytes) -> None:
        self.put(payload)

    def undeclare(self) -> None:
        """Let it go (once; a second call does nothing)."""
        if self in self._bus._held:
            self._bus._held.remove(self)
        pub, self._pub = self._pub, None
        if pub is not None:
            with contextlib.suppress(Exception):  # the session may be gone already
                pub.undeclare()


class Bus:
    """One Zenoh session and what a service declares on it (kept alive until close)."""

    def __init__(
        self,
        connect: list[str] | None = None,
        mode: str = "client",
        listen: list[str] | None = None,
        security: Security | None = None,
        acl: dict[str, Any] | None = None,
    ) -> None:
        """`security` None: from the MACB_ZENOH_* variables (none set: plain, as before)."""
        _init_logging()
        self.mode = mode
        if security is None:
            security = Security.from_env()
        config = _config(mode, connect, listen, security, acl)
        try:
            self.session = zenoh.open(config)
        except zenoh.ZError as err:
            raise BusError(open_failure(mode, connect, listen, err)) from None
        self._held: list[Any] = []  # declared entities must outlive their callbacks

    @classmethod
    def router(
        cls,
        listen: list[str],
        connect: list[str] | None = None,
        security: Security | None = None,
        acl: dict[str, Any] | None = None,
    ) -> Bus:
        """A router session; `connect` names other routers to peer with."""
        return cls(connect=connect, mode="router", listen=listen, security=security, acl=acl)

    def close(self) -> None:
        for h in reversed(list(self._held)):  # (a Publisher leaves the list as it goes)
            with contextlib.suppress(Exception):  # already undeclared or session gone
                h.undeclare()
        self._held.clear()
        self.session.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------ pub/sub
    def publisher(self, key: str, block: bool = True) -> Publisher:
        """A declared publisher on `key`, called with a payload to put it; `undeclare`
        (or `Bus.undeclare`) lets it go. BLOCK makes a congested link wait instead of
        dropping."""
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = Publisher(self, self.session.declare_publisher(key, congestion_control=cc))
        self._held.append(pub)
        return pub

    def put(self, key: str, payload: bytes, block: bool = True) -> None:
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self.session.put(key, payload, congestion_control=cc)

    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Any:
        """Declare a callback subscriber; returns a handle for `undeclare`."""

        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.payload.to_bytes())

        sub = self.session.declare_subscriber(key_expr, on_sample)
        self._held.append(sub)
        return sub

    def undeclare(self, handle: Any) -> None:
        if handle in self._held:
            self._held.remove(handle)
            with contextlib.suppress(Exception):
                handle.undeclare()

    # ------------------------------------------------------------ queries
    def queryable(
        self, key_expr: str, handler: Callable[[str, bytes], bytes | Refused | None]
    ) -> None:
        """handler(key, payload) -> reply bytes, a `Refused` (an error reply with its
        reason) or None (no reply), on Zenoh's thread."""

        concrete = "*" not in key_expr

        def on_query(query: zenoh.Query) -> None:
            # Reply on our own key when we have one: replies to a wildcard query would
            # otherwise all carry the query's key and be consolidated into one.
            with query:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                try:
                    reply = handler(str(query.key_expr), payload)
                except Exception:
                    log.exception("query handler failed on %s", query.key_expr)
                    return
                if isinstance(reply, Refused):
                    query.reply_err(reply.payload())
                elif reply is not None:
                    query.reply(key_expr if concrete else query.key_expr, reply)

        self._held.append(self.session.declare_queryable(key_expr, on_query))

    def get(self, selector: str, payload: bytes | None = None, timeout: float = 2.0) -> list[bytes]:
        """Blocking query: every ok reply's payload."""
        return self.collect_all(self.get_async(selector, payload, timeout)).ok

    @staticmethod
    def collect_all(replies: Any) -> Replies:
        """A query's ok payloads and our refusals' reasons (waiting for them); other
        error replies (Zenoh's timeout) count as no answer."""
        out = Replies()
        for r in replies:
            if r.ok:
                out.ok.append(r.ok.payload.to_bytes())
            elif r.err and (refused := Refused.read(r.err.payload.to_bytes())):
                out.refused.append(refused)
        return out

    def get_async(self, selector: str, payload: bytes | None = None, timeout: float = 2.0):
        """Start a query; iterate the returned handler later for the replies (`.ok`)."""
        kwargs: dict[str, Any] = {
            "timeout": timeout,
            "consolidation": zenoh.ConsolidationMode.NONE,
        }
        if payload is not None:
            kwargs["payload"] = payload
        return self.session.get(selector, **kwargs)

    # ------------------------------------------------------------ liveliness
    def token(self, key: str) -> None:
        self._held.append(self.session.liveliness().declare_token(key))

    def alive(self, key_expr: str, timeout: float = 1.0) -> list[str]:
        return [
            str(r.ok.key_expr)
            for r in self.session.liveliness().get(key_expr, timeout=timeout)
            if r.ok
        ]

    def watch_liveliness(self, key_expr: str, callback: Callable[[str, bool], None]) -> None:
        """callback(key, alive) on appear/disappear, including tokens alive already."""

        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        sub = self.session.liveliness().declare_subscriber(key_expr, on_sample, history=True)
        self._held.append(sub)
