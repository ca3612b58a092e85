"""The bus's security on the command line: the flags every bus command takes, and
`macb certs`, which makes a CA, certificates and credentials for a small cluster.

The flags only set the `MACB_ZENOH_*` variables (`shared.net.security.ENV`) for this
process and the processes it starts, so a flag and its variable mean the same thing
everywhere (services, the API, `macb start/ps/stop --bus`, `macb up`'s children).
`macb certs` runs `openssl` (no Python crypto dependency); docs/deploy.md shows the
same steps by hand.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import secrets
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from cli.config_flags import at_least_one
from shared.net.roles import role_of
from shared.net.security import ENV, SecurityError, read_users_file

FLAGS = (
    ("--secrets", "secrets", "DIR", "folder `macb certs` wrote (ca.pem, USER.pem/.key/.password)"),
    ("--user", "user", "NAME", "bus user name (the service id; its role comes from it)"),
    ("--password-file", "password_file", "FILE", "file holding the user's password"),
    ("--users-file", "users_file", "FILE", "router only: user:password file (auth + ACL)"),
    ("--tls-ca", "tls_ca", "FILE", "CA certificate: TLS on every link (endpoints tls/...)"),
    ("--tls-cert", "tls_cert", "FILE", "this node's certificate (router; clients with mTLS)"),
    ("--tls-key", "tls_key", "FILE", "this node's private key"),
)


def add_security_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "bus security", "each flag sets its MACB_ZENOH_* variable (docs/deploy.md)"
    )
    for flag, dest, metavar, help_ in FLAGS:
        g.add_argument(flag, dest=f"zenoh_{dest}", metavar=metavar, help=f"{help_} ({ENV[dest]})")
    g.add_argument(
        "--mtls",
        dest="zenoh_mtls",
        action="store_true",
        default=None,
        help=f"mutual TLS: every session presents a certificate ({ENV['mtls']}=1)",
    )


def apply_security_flags(args: argparse.Namespace) -> None:
    """Flags given override the variables, here and for the children this starts."""
    for _, dest, _, _ in FLAGS:
        value = getattr(args, f"zenoh_{dest}", None)
        if value is not None:
            os.environ[ENV[dest]] = str(value)
    if getattr(args, "zenoh_mtls", None):
        os.environ[ENV["mtls"]] = "1"


# ---------------------------------------------------------------- macb certs
def add_certs_parser(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser(
        "certs",
        help="make a CA, certificates and credentials for a cluster (openssl)",
        description="Write to DIR: ca.pem/ca.key (kept if present), for every router and "
        "user a certificate NAME.pem/NAME.key signed by the CA (common name NAME), for every "
        "user a password NAME.password, and users.txt (user:password, the routers' "
        "credentials file). Run again with more names to add them; existing files are kept, "
        "but a router certificate lacking a host name --router gives is re-signed with it "
        "(its key kept). "
        "Copy DIR to each host (ca.key need not leave this one).",
    )
    c.add_argument("dir", type=Path)
    c.add_argument(
        "--router",
        action="append",
        metavar="NAME[=HOST,...]",
        help="a router and the host names / IPs clients reach it by (default: router; "
        "localhost, 127.0.0.1 and NAME are always included); repeat per router",
    )
    c.add_argument("--actors", type=at_least_one, default=1, help="actor users actor0..actor{N-1}")
    c.add_argument(
        "--user",
        action="append",
        default=[],
        metavar="NAME",
        help="more users (named after their role: actor-h2-0, learner2, cli-alice)",
    )
    c.add_argument("--days", type=at_least_one, default=825, help="certificate lifetime, in days")
    c.set_defaults(func=cmd_certs)


BASE_USERS = ("counter", "learner", "evaluator", "api", "cli")


MAX_DAYS = 36_500  # a hundred years: within every openssl's date range


def cmd_certs(args: argparse.Namespace) -> int:
    if shutil.which("openssl") is None:
        print("macb certs: needs the openssl command", file=sys.stderr)
        return 2
    if args.days > MAX_DAYS:  # (openssl fails past its date range, a key already written)
        print(f"macb certs: --days {args.days}: at most {MAX_DAYS}", file=sys.stderr)
        return 2
    routers: dict[str, list[str]] = {}
    for spec in args.router or ["router"]:
        name, _, hosts = spec.partition("=")
        routers[name] = [h for h in hosts.split(",") if h]
    users = [*BASE_USERS, *(f"actor{i}" for i in range(args.actors)), *args.user, *routers]
    if Path(args.dir).exists() and not Path(args.dir).is_dir():
        print(f"macb certs: {args.dir}: a file, not a folder for the certificates", file=sys.stderr)
        return 2
    try:
        for u in users:
            role_of(u)
        for r in routers:
            if role_of(r) != "router":
                raise SecurityError(f"router {r!r}: a router's name starts with 'router'")
        made = make_certs(args.dir, routers, users, args.days)
    except (SecurityError, subprocess.CalledProcessError, OSError) as err:
        detail = getattr(err, "stderr", None) or ""
        print(f"macb certs: {err} {detail}".strip(), file=sys.stderr)
        return 2
    print(f"wrote {len(made)} files to {args.dir}/: {' '.join(made) or '(all present)'}")
    return 0


def make_certs(
    out: Path,
    routers: dict[str, list[str]],
    users: list[str],
    days: int = 825,
    say: Callable[[str], None] = print,
) -> list[str]:
    """Create what is missing in `out`; return the names of the files written. A
    router's certificate lacking a host name asked for now is re-signed with its names
    and the new ones (its key kept, so nothing else changes), and `say` tells which: a
    certificate kept as it was would fail the TLS host check on the new host."""
    out.mkdir(parents=True, exist_ok=True)
    made: list[str] = []
    ca, ca_key = out / "ca.pem", out / "ca.key"
    if not ca.exists():
        _openssl(
            "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
            "-nodes", "-keyout", ca_key, "-out", ca, "-days", str(days * 2),
            "-subj", "/CN=macb-ca", "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        )  # fmt: skip
        ca_key.chmod(0o600)
        made += ["ca.pem", "ca.key"]
    elif not ca_key.exists():
        raise SecurityError(f"{ca} exists but {ca_key} does not: cannot sign new certificates")
    for name in dict.fromkeys([*routers, *users]):
        wanted = _sans(["localhost", "127.0.0.1", name, *routers.get(name, [])])
        cert = out / f"{name}.pem"
        if not cert.exists():
            _sign(out, name, wanted, days)
            made += [f"{name}.pem", f"{name}.key"]
            continue
        # Only host names asked for by --router re-sign a certificate: one made by hand
        # without the defaults (localhost, ...) is the user's choice and stays as it is.
        asked = _sans(routers.get(name, []))
        have = _cert_sans(cert) if asked else []
        if lacking := [s for s in asked if s not in have]:
            _sign(out, name, list(dict.fromkeys([*have, *wanted])), days, keep_key=True)
            made.append(cert.name)
            say(
                f"{cert.name}: re-signed to add {', '.join(lacking)}, its key kept; copy it "
                f"to the host that runs {name} and restart it there"
            )
    table_path = out / "users.txt"
    table = read_users_file(table_path) if table_path.exists() else {}
    for name in users:
        pw_file = out / f"{name}.password"
        if not pw_file.exists():
            _write_secret(pw_file, table.get(name) or secrets.token_urlsafe(24))
            made.append(pw_file.name)
        table[name] = pw_file.read_text().strip()
    text = "".join(f"{u}:{p}\n" for u, p in table.items())
    if not table_path.exists() or table_path.read_text() != text:
        _write_secret(table_path, text)
        made.append("users.txt")
    return made


def _sans(hosts: list[str]) -> list[str]:
    """Host names and IPs as subjectAltName entries (`DNS:a.example`, `IP:10.0.0.5`), an
    IP in its compressed form so that it compares equal to what openssl prints."""
    sans: list[str] = []
    for h in hosts:
        try:
            sans.append(f"IP:{ipaddress.ip_address(h).compressed}")
        except ValueError:
            sans.append(f"DNS:{h.lower()}")
    return list(dict.fromkeys(sans))


def _cert_sans(cert: Path) -> list[str]:
    """The subjectAltName entries `cert` carries, as `_sans` writes them (none: [])."""
    got = subprocess.run(
        ["openssl", "x509", "-in", str(cert), "-noout", "-ext", "subjectAltName"],
        capture_output=True, text=True,
    )  # fmt: skip
    if got.returncode:
        last = (got.stderr.strip().splitlines() or ["openssl failed"])[-1]
        raise SecurityError(f"certificate {cert}: cannot read it ({last})")
    lines = got.stdout.splitlines()[1:]  # after the "X509v3 Subject Alternative Name:" line
    entries = [e.strip() for line in lines for e in line.split(",") if e.strip()]
    hosts = [e.split(":", 1)[1] for e in entries if e.startswith(("DNS:", "IP Address:"))]
    return _sans(hosts)


def _sign(out: Path, name: str, sans: list[str], days: int, keep_key: bool = False) -> None:
    """Sign NAME.pem for `sans` with the CA; `keep_key`: for the key NAME.key already
    holds (a re-signed certificate), else for a new one."""
    key, cert = out / f"{name}.key", out / f"{name}.pem"
    if keep_key and not key.exists():
        raise SecurityError(
            f"{cert} needs re-signing for more host names but its key {key} is missing "
            f"(remove {cert} to make a new pair)"
        )
    with tempfile.TemporaryDirectory() as tmp:
        csr, ext = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        ext.write_text(
            f"subjectAltName={','.join(sans)}\nbasicConstraints=CA:FALSE\n"
            "keyUsage=critical,digitalSignature,keyEncipherment\n"
            "extendedKeyUsage=serverAuth,clientAuth\n"
        )
        if keep_key:
            _openssl("req", "-new", "-key", key, "-out", csr, "-subj", f"/CN={name}")
        else:
            _openssl(
                "req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                "-keyout", key, "-out", csr, "-subj", f"/CN={name}",
            )  # fmt: skip
        _openssl(
            "x509", "-req", "-in", csr, "-CA", out / "ca.pem", "-CAkey", out / "ca.key",
            "-CAcreateserial", "-out", cert, "-days", str(days), "-extfile", ext,
        )  # fmt: skip
    key.chmod(0o600)
    (out / "ca.srl").unlink(missing_ok=True)


def _write_secret(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text if text.endswith("\n") else text + "\n")


def _openssl(*args: object) -> None:
    subprocess.run(["openssl", *map(str, args)], check=True, capture_output=True, text=True)
