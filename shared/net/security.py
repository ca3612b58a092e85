"""The bus's security settings, as pure config building: TLS, user/password, listening.

Zenoh does the work (TLS links, `transport/auth/usrpwd`, `access_control` on the router);
this module decides what to ask of it: the TLS and password settings, where a router
may listen, and reading the ACL's denials from zenoh's log. What each role may do on
the key space is the policy in shared/net/roles.py (`ROLES`, `acl_config`). Nothing
here imports zenoh or touches the network: `shared/net/bus.py` turns `zenoh_config`
into a session, and the router (services/router/main.py) adds `acl_config`.

Settings come from `MACB_ZENOH_*` variables (the `macb` flags set the same variables),
so every service, the API and the CLI configure their sessions the same way. With none
set, nothing changes: plain TCP on loopback, no credentials (what `make run` uses).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.net.roles import SecurityError, acl_config, role_of
from shared.settings import Settings, settings


class BusError(RuntimeError):
    """A session could not open: no router answers at the endpoints, or the port a
    router would listen on is taken. Raised by shared/net/bus.py; defined here, where
    zenoh is not imported, so the command line can catch it without loading zenoh."""


# ---------------------------------------------------------------- settings
# Each setting's variable (`shared.settings.Settings`' zenoh_* fields), by its name here.
ENV = {
    k: Settings.env_name(f"zenoh_{k}")
    for k in (
        "secrets",
        "user",
        "password",
        "password_file",
        "users_file",
        "tls_ca",
        "tls_cert",
        "tls_key",
        "mtls",
    )
}


@dataclass(frozen=True)
class Security:
    """One session's security settings (all None: plain, unauthenticated, as before).

    `secrets` is a folder laid out as `macb certs` writes it (ca.pem, USER.pem,
    USER.key, USER.password, users.txt); each file not set explicitly is taken from it
    when it exists there. A router uses `users_file` (Zenoh's `user:password`
    dictionary) to authenticate sessions and to build its ACL; every session uses
    `user` and its password to authenticate (a router, towards the routers it connects
    to). TLS needs the CA (`tls_ca`) everywhere, a certificate and key on a router
    (what it presents when listening, and when it connects with mTLS), and with `mtls`
    a client certificate and key on every session.
    """

    user: str | None = None
    password: str | None = field(default=None, repr=False)
    password_file: Path | None = None
    users_file: Path | None = None
    tls_ca: Path | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None
    mtls: bool = False
    secrets: Path | None = None

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> Security:
        """The settings of MACB_ZENOH_* in `env` (default: the process's environment, as
        it is now); an empty variable counts as unset."""
        s = settings() if env is None else Settings.of(env)
        raw = {k: getattr(s, f"zenoh_{k}") or None for k in ENV}
        secrets = Path(raw["secrets"]) if raw["secrets"] else None
        if secrets is not None and not secrets.is_dir():
            raise SecurityError(f"{ENV['secrets']}={secrets}: no such directory")
        user = raw["user"]

        def path(key: str, default_name: str | None) -> Path | None:
            if value := raw[key]:
                return Path(value)
            if secrets is not None and default_name and (secrets / default_name).exists():
                return secrets / default_name
            return None

        mtls_raw = (raw["mtls"] or "").strip().lower()
        if mtls_raw not in ("", "0", "1", "true", "false", "yes", "no"):
            raise SecurityError(f"{ENV['mtls']}={raw['mtls']}: want 1 or 0")
        return cls(
            user=user,
            password=raw["password"],
            password_file=path(
                "password_file", f"{user}.password" if user and not raw["password"] else None
            ),
            users_file=path("users_file", None),
            tls_ca=path("tls_ca", "ca.pem"),
            tls_cert=path("tls_cert", f"{user}.pem" if user else None),
            tls_key=path("tls_key", f"{user}.key" if user else None),
            mtls=mtls_raw in ("1", "true", "yes"),
            secrets=secrets,
        )

    def for_router(self) -> Security:
        """The router also takes the cluster's users file from the secrets folder."""
        if self.users_file is None and self.secrets is not None:
            candidate = self.secrets / "users.txt"
            if candidate.exists():
                return dataclasses.replace(self, users_file=candidate)
        return self

    @property
    def tls(self) -> bool:
        return self.tls_ca is not None

    @property
    def configured(self) -> bool:
        fields = (self.user, self.password, self.password_file, self.users_file, self.tls_ca)
        return any((*fields, self.tls_cert, self.tls_key, self.mtls))

    # ------------------------------------------------------------ checks
    def check(self, mode: str) -> None:
        """Refuse (SecurityError naming the file or the variable) anything that would
        make a session fail later or run less protected than asked. Call before any
        session opens, so nothing half-starts."""
        router = mode == "router"
        if self.password is not None and self.password_file is not None:
            raise SecurityError(
                f"both {ENV['password']} and {ENV['password_file']} ({self.password_file}) "
                "are set: use one"
            )
        has_password = self.password is not None or self.password_file is not None
        if has_password and not self.user:
            raise SecurityError(f"a password is set but no user: set {ENV['user']}")
        if self.user and not has_password:
            hint = f" (no {self.user}.password in {self.secrets})" if self.secrets else ""
            raise SecurityError(
                f"user {self.user!r} has no password: set {ENV['password_file']} "
                f"or {ENV['password']}{hint}"
            )
        if self.user:
            role_of(self.user)
        if self.password_file is not None:
            text = _read(self.password_file, "password file").strip()
            if not text or "\n" in text:
                raise SecurityError(f"password file {self.password_file}: want one line")
        if self.users_file is not None:
            if not router:
                raise SecurityError(
                    f"{ENV['users_file']} ({self.users_file}) is for the router only"
                )
            read_users_file(self.users_file)
        if (self.tls_cert is None) != (self.tls_key is None):
            have, miss = ("certificate", "key") if self.tls_key is None else ("key", "certificate")
            raise SecurityError(
                f"a TLS {have} without its {miss}: set {ENV['tls_cert']} and {ENV['tls_key']}"
            )
        if (self.tls_cert or self.mtls) and not self.tls_ca:
            raise SecurityError(f"TLS certificates or mTLS without a CA: set {ENV['tls_ca']}")
        if self.tls_ca is not None:
            _check_pem(self.tls_ca, "CA certificate", "CERTIFICATE")
        if self.tls_cert is not None and self.tls_key is not None:
            _check_pem(self.tls_cert, "TLS certificate", "CERTIFICATE")
            _check_pem(self.tls_key, "TLS key", "PRIVATE KEY")
        if self.tls and router and self.tls_cert is None:
            hint = f" (or {self.user}.pem in {self.secrets})" if self.secrets else ""
            raise SecurityError(
                f"a TLS router needs its certificate and key: set {ENV['tls_cert']} and "
                f"{ENV['tls_key']}{hint}"
            )
        if self.mtls and self.tls_cert is None:
            raise SecurityError(
                f"mTLS: this session needs a client certificate and key: set "
                f"{ENV['tls_cert']} and {ENV['tls_key']}"
            )

    def password_value(self) -> str | None:
        if self.password_file is not None:
            return _read(self.password_file, "password file").strip()
        return self.password

    # ------------------------------------------------------------ zenoh config
    def zenoh_config(self, mode: str) -> dict[str, Any]:
        """The `transport` section for a session in `mode` (router or client); {} when
        nothing is configured. Run `check(mode)` first."""
        transport: dict[str, Any] = {}
        if self.tls_ca is not None:
            tls: dict[str, Any] = {"root_ca_certificate": str(self.tls_ca)}
            if self.tls_cert is not None and self.tls_key is not None:
                if mode == "router":
                    tls["listen_certificate"] = str(self.tls_cert)
                    tls["listen_private_key"] = str(self.tls_key)
                tls["connect_certificate"] = str(self.tls_cert)
                tls["connect_private_key"] = str(self.tls_key)
            if self.mtls:
                tls["enable_mtls"] = True
            transport["link"] = {"tls": tls}
        usrpwd: dict[str, Any] = {}
        if self.user:
            usrpwd["user"] = self.user
            usrpwd["password"] = self.password_value()
        if mode == "router" and self.users_file is not None:
            usrpwd["dictionary_file"] = str(self.users_file)
        if usrpwd:
            transport["auth"] = {"usrpwd": usrpwd}
        return {"transport": transport} if transport else {}

    def router_acl(self) -> dict[str, Any] | None:
        """The router's `access_control` section: every user of the users file."""
        if self.users_file is None:
            return None
        return acl_config(list(read_users_file(self.users_file)))


def _read(path: Path, what: str) -> str:
    try:
        return Path(path).read_text()
    except FileNotFoundError:
        raise SecurityError(f"{what} {path}: no such file") from None
    except (PermissionError, IsADirectoryError, UnicodeDecodeError, OSError) as err:
        raise SecurityError(f"{what} {path}: cannot read it ({err.__class__.__name__})") from None


def _check_pem(path: Path, what: str, label: str) -> None:
    text = _read(path, what)
    if f"-----BEGIN {label}-----" not in text and not (
        label == "PRIVATE KEY" and re.search(r"-----BEGIN [A-Z ]*PRIVATE KEY-----", text)
    ):
        raise SecurityError(f"{what} {path}: not a PEM {label.lower()}")


def read_users_file(path: Path) -> dict[str, str]:
    """Zenoh's usrpwd dictionary (`user:password`, one a line): user -> password.
    Every user must name a role; a malformed line is refused with its number."""
    users: dict[str, str] = {}
    for n, line in enumerate(_read(path, "users file").splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not user or not password:
            raise SecurityError(f"users file {path}, line {n}: want user:password")
        if user in users:
            raise SecurityError(f"users file {path}, line {n}: user {user!r} again")
        try:
            role_of(user)
        except SecurityError as err:
            raise SecurityError(f"users file {path}, line {n}: {err}") from None
        users[user] = password
    if not users:
        raise SecurityError(f"users file {path}: no users")
    return users


# ---------------------------------------------------------------- where a router may listen
def endpoint_host(endpoint: str) -> tuple[str, str]:
    """(protocol, host) of a Zenoh endpoint like `tls/10.0.0.5:7447` or `tcp/[::1]:7447`."""
    proto, sep, rest = endpoint.partition("/")
    if not sep:
        raise SecurityError(f"endpoint {endpoint!r}: want PROTO/HOST:PORT")
    addr = rest.split("#", 1)[0].split("?", 1)[0]
    host = addr.rsplit(":", 1)[0] if ":" in addr else addr
    return proto, host.strip("[]")


def is_loopback_host(host: str) -> bool:
    """127.0.0.0/8, ::1 and `localhost`: what only this machine can reach."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_router_listen(listen: list[str], sec: Security) -> None:
    """A router listening beyond loopback needs TLS on that endpoint and user/password
    authentication (with its ACL); raise SecurityError saying what is missing."""
    for ep in listen:
        proto, host = endpoint_host(ep)
        if is_loopback_host(host):
            continue
        missing = []
        if proto != "tls":
            missing.append(f"a tls/ endpoint (not {proto}/)")
        if not sec.tls or sec.tls_cert is None:
            missing.append(f"TLS ({ENV['tls_ca']}, {ENV['tls_cert']}, {ENV['tls_key']})")
        if sec.users_file is None:
            missing.append(f"authentication ({ENV['users_file']}: the user:password file)")
        if missing:
            raise SecurityError(
                f"refusing to listen on {ep}: not a loopback address, and "
                + "; ".join(missing)
                + " missing (`macb certs DIR` makes them; see docs/deploy.md)"
            )


def check_endpoints_match(endpoints: list[str], sec: Security) -> None:
    """With TLS configured, a non-loopback tcp/ endpoint would bypass it: refuse."""
    for ep in endpoints:
        proto, host = endpoint_host(ep)
        if sec.tls and proto == "tcp" and not is_loopback_host(host):
            raise SecurityError(
                f"TLS is configured but endpoint {ep} is plain tcp/: use tls/{ep.split('/', 1)[1]}"
            )


# ---------------------------------------------------------------- the router's denials
@dataclass(frozen=True)
class Denial:
    """One message the router's ACL dropped: who (user, or the session id when the log
    line does not name one), what (`Put`, `Declare/Undeclare Subscriber`, ...), which
    way (ingress: sent by that session; egress: meant for it) and on which key."""

    user: str
    what: str
    flow: str
    key: str


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_THREAD = re.compile(r"ThreadId\((\d+)\)")
_USER = re.compile(r"([0-9a-f]+) on \S*Username\(([^)]*)\)")
_DECISION = re.compile(
    r"(?P<cached>Using cached result: )?(?P<zid>[0-9a-f]+)(?: on \S+)? is "
    r"(?P<verdict>authorized|unauthorized) to (?P<what>.+?) \((?P<flow>ingress|egress)\) "
    r"on (?P<key>\S+)"
)
ACL_LOG_TARGET = "zenoh::net::routing::interceptor::access_control"


class AclLog:
    """Reads the denials out of Zenoh's access-control log (its TRACE lines; Zenoh
    1.10 has no other account of them, and no counter without its `stats` feature).

    Zenoh logs a decision for each message it checks, and also, when a session declares
    a key expression, the decision it caches for each of the 9 message kinds on it
    ("caching permissions for ..."): those are verdicts for messages that may never
    come, so a cache block (the lines after its header, on the same thread, up to the
    last kind, Declare Liveliness Subscriber) is not counted. Decisions taken from the
    cache ("Using cached result") name the session id only; the user is learnt from the
    lines that name both."""

    def __init__(self) -> None:
        self.users: dict[str, str] = {}  # session id -> user name
        self._caching: set[str] = set()  # threads inside a cache block

    def feed(self, line: str) -> Denial | None:
        line = _ANSI.sub("", line)
        if ACL_LOG_TARGET not in line:
            return None
        t = _THREAD.search(line)
        thread = t.group(1) if t else ""
        if "caching permissions for" in line:
            self._caching.add(thread)
            return None
        u = _USER.search(line)
        if u:
            self.users[u.group(1)] = u.group(2)
        d = _DECISION.search(line)
        if d is None:
            return None
        if thread in self._caching and not d.group("cached"):
            if d.group("what") == "Declare Liveliness Subscriber":
                self._caching.discard(thread)
            return None
        if d.group("verdict") != "unauthorized":
            return None
        zid = d.group("zid")
        return Denial(self.users.get(zid, zid), d.group("what"), d.group("flow"), d.group("key"))
