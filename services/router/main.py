"""The Zenoh router: a Python session in router mode that every service connects to.

On loopback with no settings it is the plain router of one machine. Listening anywhere
else it refuses to start unless TLS and user/password authentication are configured
(`shared.net.security.check_router_listen`); with a users file it enforces the per-role
ACL built from `shared.net.roles.ROLES`. The ACL's denials are logged here (the first of
each kind at once, then a summary at most every 10 s) and counted; the counts answer
queries on `macb/router/{id}` (`macb ps` shows them). The run goes on: a denied
message is dropped, nothing else happens to its sender.
"""

from __future__ import annotations

import collections
import json
import logging
import signal
import threading
import time
from typing import Any

from shared.net.bus import Bus, capture_zenoh_log, k_router
from shared.net.roles import role_of
from shared.net.security import (
    ACL_LOG_TARGET,
    AclLog,
    Denial,
    Security,
    SecurityError,
    check_router_listen,
)

log = logging.getLogger("macb.router")


class Denials:
    """The ACL's denials counted by (user, what, flow, key); logged rate-limited."""

    summary_s = 10.0

    def __init__(self) -> None:
        self.parser = AclLog()
        self.counts: collections.Counter[Denial] = collections.Counter()
        self._lock = threading.Lock()
        self._last_summary = 0.0
        self._since_summary = 0

    def on_line(self, line: str) -> None:
        denial = self.parser.feed(line)
        if denial is None:
            return
        with self._lock:
            first = denial not in self.counts
            self.counts[denial] += 1
            total = sum(self.counts.values())
            self._since_summary += 1
            now = time.monotonic()
            due = now - self._last_summary >= self.summary_s
            if due:
                self._last_summary, since, self._since_summary = now, self._since_summary, 0
        if first:
            log.warning(
                "ACL denied: %s %s (%s) on %s (%s)",
                _who(denial.user),
                denial.what,
                denial.flow,
                denial.key,
                f"{total} denied so far",
            )
        elif due:
            log.warning("ACL: %d denied in %.0f s, %d in all", since, self.summary_s, total)

    def snapshot(self) -> dict:
        with self._lock:
            rows = [
                {"user": d.user, "what": d.what, "flow": d.flow, "key": d.key, "count": n}
                for d, n in self.counts.most_common()
            ]
        return {"denied_total": sum(r["count"] for r in rows), "denied": rows}


def _who(user: str) -> str:
    try:
        return f"user {user} ({role_of(user)})"
    except ValueError:
        return f"session {user}"


def serve(
    listen: list[str],
    connect: list[str] | None = None,
    router_id: str = "router",
    security: Security | None = None,
) -> None:
    """Run the router until SIGTERM/SIGINT. Raises SecurityError before any session
    opens when the settings are incomplete or a file is unusable."""
    sec = (security or Security.from_env()).for_router()
    sec.check("router")
    check_router_listen(listen, sec)
    if connect and sec.users_file is not None and not sec.user:
        raise SecurityError(
            "a router that connects to other routers signs in there: set MACB_ZENOH_USER "
            "(a router user of the users file, e.g. router-b)"
        )
    acl = sec.router_acl()
    denials = Denials() if acl is not None else None
    if denials is not None:
        capture_zenoh_log(ACL_LOG_TARGET, denials.on_line)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    with Bus.router(listen, connect=connect, security=sec, acl=acl) as bus:

        def stats(key: str, payload: bytes) -> bytes:
            body: dict[str, Any] = {"id": router_id, "listen": listen, "connect": connect or []}
            body["acl"] = acl is not None
            body.update(denials.snapshot() if denials else {"denied_total": 0, "denied": []})
            return json.dumps(body).encode()

        bus.queryable(k_router(router_id), stats)
        secured = ["TLS"] * sec.tls + ["user/password"] * (sec.users_file is not None)
        if acl is not None:
            secured.append(f"ACL for {len(acl['policies'])} users")
        log.info(
            "router %s listening on %s%s; %s",
            router_id,
            ", ".join(listen),
            f", connecting to {', '.join(connect)}" if connect else "",
            ", ".join(secured) or "no TLS, no authentication (loopback only)",
        )
        done.wait()
    log.info("router stopped")
