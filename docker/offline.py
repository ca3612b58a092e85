"""The project's image built without a registry, on a docker engine this script can start.

Why: the project machines reach package mirrors (Debian, PyPI) but no image registry,
and have no docker engine running. This builds what `docker pull python:3.11-slim`
would have given (a Debian bookworm base from `debootstrap`, whose python3 is 3.11),
then the project image from the Dockerfile with the base and the torch source as build
arguments: the CPU torch wheel pip's `find-links` names, the host's CA bundle for pip.
Both images are tagged by a digest of what goes into them, so an unchanged tree builds
nothing the second time. tests/test_compose.py (`make test-compose`) uses it; so can a
user (README, "Containers without a registry"):

    python3 docker/offline.py engine     # install docker.io etc. (root), start dockerd
    python3 docker/offline.py image      # base + project image, tagged macb:latest too

Standard library only, so it runs before any virtualenv exists.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOCAL = ROOT / "docker" / "local"  # gitignored: the wheel and CA bundle for the build
SUITE = "bookworm"  # its python3 is 3.11, the version pyproject.toml requires
MIRROR = "http://deb.debian.org/debian"
BASE_PACKAGES = ("python3", "python3-venv", "ca-certificates")
# Debian package -> the program it provides.
ENGINE_PACKAGES = {"docker.io": "dockerd", "docker-compose": "docker-compose"}
BASE_TOOLS = {"debootstrap": "debootstrap"}
# No bridge network, no iptables rules, no forwarding: containers use the host network.
DOCKERD_ARGS = ("--bridge=none", "--iptables=false", "--ip-forward=false")
HOST_CA = Path("/etc/ssl/certs/ca-certificates.crt")


class Unavailable(RuntimeError):
    """Docker cannot be had here; the message says why (tests skip with it)."""


class BuildFailed(RuntimeError):
    """A step of building an image failed; the message has the command and its output."""


def run(argv: list[str], timeout: float = 1800, **kw) -> subprocess.CompletedProcess:
    """Run a command, raising BuildFailed with its output tail when it fails."""
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kw)
    if proc.returncode != 0:
        tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-40:])
        raise BuildFailed(f"{' '.join(argv[:6])} ... exited {proc.returncode}:\n{tail}")
    return proc


# ---------------------------------------------------------------- the engine
@dataclass
class Engine:
    """A docker engine that answers: the clients to use, and the dockerd we started
    (None when one was already running, which is then left alone)."""

    docker: str
    compose: list[str]
    started: subprocess.Popen | None = None

    def stop(self) -> None:
        """Stop the dockerd this process started (SIGTERM, then SIGKILL after 60 s)."""
        if self.started is None or self.started.poll() is not None:
            return
        self.started.terminate()
        try:
            self.started.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.started.kill()
            self.started.wait()


def docker_cli() -> str | None:
    """Debian's client beside its engine when installed (same API version), else PATH's."""
    return "/usr/bin/docker" if os.access("/usr/bin/docker", os.X_OK) else shutil.which("docker")


def compose_cli(docker: str | None) -> list[str] | None:
    """`docker-compose` (v1, Debian's 1.29) if installed, else the v2 plugin, else None."""
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if docker and subprocess.run([docker, "compose", "version"], capture_output=True).returncode:
        return None
    return [docker, "compose"] if docker else None


def engine_answers(docker: str | None) -> bool:
    if docker is None:
        return False
    try:
        return subprocess.run([docker, "info"], capture_output=True, timeout=30).returncode == 0
    except subprocess.TimeoutExpired:
        return False


def missing_packages(wanted: dict[str, str]) -> list[str]:
    return [pkg for pkg, prog in wanted.items() if shutil.which(prog) is None]


def install(packages: list[str]) -> None:
    """apt-get install the Debian packages (root only; the caller checked)."""
    if not packages:
        return
    if shutil.which("apt-get") is None:
        raise Unavailable(f"{', '.join(packages)} missing and no apt-get to install them")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    run(["apt-get", "update", "-qq"], timeout=600, env=env)
    run(["apt-get", "install", "-y", "-qq", "--no-install-recommends", *packages], env=env)


def ensure_engine(log: Path, may_set_up: bool) -> Engine:
    """A docker engine and compose that answer. With `may_set_up` (make test-compose),
    as root: install what is missing and start dockerd without bridge networking, its
    log in `log`. Raises Unavailable saying why not."""
    docker = docker_cli()
    compose = compose_cli(docker)
    if engine_answers(docker) and compose and not missing_packages(BASE_TOOLS):
        return Engine(docker, compose)
    if not may_set_up:
        lacking = [] if engine_answers(docker) else ["no docker engine answers"]
        lacking += [] if compose else ["no docker-compose"]
        lacking += [f"no {p}" for p in missing_packages(BASE_TOOLS)]
        raise Unavailable(
            f"{', '.join(lacking)} (`make test-compose` installs and starts them, as root)"
        )
    if os.geteuid() != 0:
        raise Unavailable("installing docker.io and starting dockerd needs root")
    install(missing_packages({**ENGINE_PACKAGES, **BASE_TOOLS}))
    docker, compose = docker_cli(), compose_cli(docker_cli())
    assert docker and compose, "docker.io and docker-compose were just installed"
    if engine_answers(docker):
        return Engine(docker, compose)
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("ab") as out:
        proc = subprocess.Popen(
            ["dockerd", *DOCKERD_ARGS],
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
    engine = Engine(docker, compose, proc)
    deadline = time.monotonic() + 90
    while not engine_answers(docker):
        if proc.poll() is not None or time.monotonic() > deadline:
            engine.stop()
            tail = log.read_text(errors="replace").splitlines()[-20:]
            raise Unavailable("dockerd did not come up:\n" + "\n".join(tail))
        time.sleep(0.5)
    return engine


# ---------------------------------------------------------------- images
def image_exists(docker: str, tag: str) -> bool:
    return subprocess.run([docker, "image", "inspect", tag], capture_output=True).returncode == 0


def base_tag() -> str:
    """The base's tag, a digest of what debootstrap is asked for."""
    spec = f"{SUITE} minbase {MIRROR} {','.join(BASE_PACKAGES)}"
    return f"macb-base:{SUITE}-{hashlib.sha256(spec.encode()).hexdigest()[:12]}"


def ensure_base(docker: str) -> str:
    """A Debian bookworm image (debootstrap minbase + python3, venv, CA certificates),
    made once and kept under its tag; what `python:3.11-slim` is to a user outside."""
    tag = base_tag()
    if image_exists(docker, tag):
        return tag
    if os.geteuid() != 0:
        raise Unavailable(f"building {tag} with debootstrap needs root")
    with tempfile.TemporaryDirectory(prefix="macb-base-") as tmp:
        rootfs = Path(tmp) / "rootfs"
        run(
            [
                "debootstrap",
                "--variant=minbase",
                f"--include={','.join(BASE_PACKAGES)}",
                SUITE,
                str(rootfs),
                MIRROR,
            ],
            timeout=1200,
        )
        for junk in ("var/cache/apt/archives", "var/lib/apt/lists"):
            for p in (rootfs / junk).glob("*"):
                if p.is_file():
                    p.unlink()
        tar = subprocess.Popen(["tar", "-C", str(rootfs), "-c", "."], stdout=subprocess.PIPE)
        run([docker, "import", "-", tag], stdin=tar.stdout)
        tar.wait()
    return tag


def torch_pin() -> str:
    """torch's pin from pyproject.toml (`torch==2.13.0`), the one place pins live."""
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    pins = [d for d in deps if re.match(r"torch\s*==", d)]
    if len(pins) != 1:
        raise BuildFailed(f"pyproject.toml pins torch {len(pins)} times, not once: {pins}")
    return pins[0].replace(" ", "")


def find_links() -> list[Path]:
    """The directories pip's find-links setting names (env, then `pip config list`)."""
    values = os.environ.get("PIP_FIND_LINKS", "").split()
    try:
        listing = subprocess.run(
            [sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True
        ).stdout
    except OSError:
        listing = ""
    for line in listing.splitlines():
        key, _, value = line.partition("=")
        if key.endswith("find-links"):
            values += value.strip("'\"").split()
    return [Path(v.removeprefix("file://")) for v in values if "://" not in v or v[:7] == "file://"]


def torch_wheel() -> Path:
    """The pinned torch's CPU wheel for CPython 3.11 in a find-links directory."""
    version = torch_pin().split("==")[1]
    pattern = f"torch-{version}+cpu-cp311-cp311-*linux*_x86_64.whl"
    for d in find_links():
        hits = sorted(d.glob(pattern))
        if hits:
            return hits[-1]
    raise Unavailable(f"no {pattern} in pip's find-links ({[str(d) for d in find_links()]})")


def context_files(root: Path = ROOT) -> list[Path]:
    """What goes into the build context: the paths .dockerignore lets through (its "!"
    lines), without Python's caches."""
    roots = [
        line[1:].strip()
        for line in (root / ".dockerignore").read_text().splitlines()
        if line.startswith("!")
    ]
    files: list[Path] = []
    for r in roots:
        p = root / r
        found = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file())
        files += [q for q in found if "__pycache__" not in q.parts and q.suffix != ".pyc"]
    return files


def context_digest(base_id: str, args: dict[str, str], root: Path = ROOT) -> str:
    """A digest of the base image's id, the build arguments, the Dockerfile and every
    context file (a wheel by name and size: 190 MB, and its name says which build)."""
    h = hashlib.sha256(f"{base_id}\n{sorted(args.items())}\n".encode())
    for f in [root / "Dockerfile", root / ".dockerignore", *context_files(root)]:
        h.update(f"{f.relative_to(root)}\n".encode())
        if f.suffix == ".whl":
            h.update(f"{f.stat().st_size}\n".encode())
        else:
            h.update(f.read_bytes())
    return h.hexdigest()[:12]


def stage_local_files() -> dict[str, str]:
    """Put the torch wheel and the host's CA bundle in docker/local/ (the build
    context); the build arguments that make the Dockerfile use them."""
    wheel = torch_wheel()
    LOCAL.mkdir(parents=True, exist_ok=True)
    for old in LOCAL.glob("torch-*.whl"):
        if old.name != wheel.name:
            old.unlink()
    target = LOCAL / wheel.name
    if not target.exists() or target.stat().st_size != wheel.stat().st_size:
        shutil.copyfile(wheel, target)
    args = {"TORCH_SOURCE": "--no-index --find-links /tmp/local --no-deps"}
    if HOST_CA.is_file():
        shutil.copyfile(HOST_CA, LOCAL / "ca-certificates.crt")
        args["PIP_CA"] = "ca-certificates.crt"
    return args


def image_tag(docker: str, base: str, args: dict[str, str]) -> str:
    """macb:<context_digest>: the same tag for the same inputs, a new one for any change."""
    base_id = run([docker, "image", "inspect", "-f", "{{.Id}}", base]).stdout.strip()
    return f"macb:{context_digest(base_id, args)}"


@dataclass
class Built:
    tag: str
    base: str
    seconds: float  # finding or building both images
    base_seconds: float  # of which finding or making the base
    cached: bool  # the project image was there under its tag


def ensure_image(docker: str) -> Built:
    """The project image built offline (base from debootstrap, torch from the local
    wheel, pip through the host network and CA bundle), cached under its digest tag."""
    t0 = time.monotonic()
    base = ensure_base(docker)
    base_s = time.monotonic() - t0
    args = {"BASE_IMAGE": base, **stage_local_files()}
    tag = image_tag(docker, base, args)
    if image_exists(docker, tag):
        return Built(tag, base, time.monotonic() - t0, base_s, cached=True)
    argv = [docker, "build", "--network", "host", "-t", tag]
    for k, v in args.items():
        argv += ["--build-arg", f"{k}={v}"]
    run(["nice", *argv, str(ROOT)], timeout=1800, env={**os.environ, "DOCKER_BUILDKIT": "0"})
    return Built(tag, base, time.monotonic() - t0, base_s, cached=False)


def image_size(docker: str, tag: str) -> int:
    return int(run([docker, "image", "inspect", "-f", "{{.Size}}", tag]).stdout)


# ---------------------------------------------------------------- command line
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("engine", help="install docker.io etc. if missing, start dockerd")
    e.add_argument("--log", default="/var/log/macb-dockerd.log", help="dockerd's log")
    sub.add_parser("image", help="build (or find) the images; tag macb:latest")
    args = p.parse_args(argv)
    try:
        if args.cmd == "engine":
            engine = ensure_engine(Path(args.log), may_set_up=True)
            how = f"started (pid {engine.started.pid}, log {args.log})" if engine.started else ""
            print(f"docker engine answers {how}".strip())
            return 0
        docker = docker_cli()
        if not engine_answers(docker):
            raise Unavailable("no docker engine answers (python3 docker/offline.py engine)")
        assert docker is not None
        built = ensure_image(docker)
        run([docker, "tag", built.tag, "macb:latest"])  # the name docker-compose.yml uses
        state = "cached" if built.cached else f"built in {built.seconds:.0f} s"
        size = image_size(docker, built.tag) / 1e6
        print(f"{built.tag} ({state}, {size:.0f} MB), tagged macb:latest")
        return 0
    except (Unavailable, BuildFailed) as err:
        print(f"offline.py: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
