"""`macb up`: the local cluster as plain processes, the same services docker-compose runs.

`cluster_plan` is the single description of the cluster: which services, with which
`macb serve` command and environment. `macb up` runs it as child processes;
docker-compose.yml runs the same commands in containers (a test keeps the two in
step). Children get one torch/BLAS thread each: on a 2-core machine shared by all
services, more threads only make them fight.

Supervision: a child that dies is started again with the same command (same id and
data dir, so it rejoins its run) after a backoff of 0.5 s doubling to 10 s, with
MACB_RESTARTS telling it how often (`macb ps` and the API's /workers show it); one
that dies RESTART_LIMIT times within RESTART_WINDOW_S is given up and `macb up`
stops, naming it. `DATA_DIR/cluster.json` lists each child's PID and restarts.

Shutdown: Ctrl-C or SIGTERM stops the children with SIGTERM (they flush snapshots and
checkpoints), waits, and SIGKILLs whatever is left, so no process outlives `macb up`.
Killed itself (SIGKILL, the OOM killer), `macb up` can end nothing: each child dies with
it anyway (MACB_PARENT_PID, `shared.procs.die_with_env_parent`: PR_SET_PDEATHSIG, armed
first thing in the child, which then checks its parent is still there). The death signal
follows the thread that started the child, so `start` and `supervise` run on the main
thread (as `macb up`, `macb serve slot` and the benchmarks call them). Children are
started and ended by PID with `shared.procs`, as the tests and the benchmarks do.

Ports: before anything starts, the router's and the API's ports must be free (`PortInUse`
names one that is not): the router and the API would fail to bind, while every readiness
check passed against whoever listens there, and the services would join that other
cluster under the same ids. A port that answers counts only while our own child lives.
"""

from __future__ import annotations

import collections
import errno
import json
import os
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from cli import forkserver
from shared import procs

RESTART_LIMIT = 5  # deaths of one service within RESTART_WINDOW_S: it is given up
RESTART_WINDOW_S = 60.0
BACKOFF_S = (0.5, 10.0)  # first restart delay, doubling up to the second
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@dataclass(frozen=True)
class ServiceSpec:
    name: str
    args: tuple[str, ...]  # after `macb serve`
    env: tuple[tuple[str, str], ...] = ()


def cluster_plan(
    actors: int = 1,
    endpoint: str = "tcp/127.0.0.1:7447",
    data_dir: str = "data",
    listen: str | None = None,
    api: str | None = "127.0.0.1:8000",
    slots: int = 1,
    secrets: str | None = None,
    group_size: int = 1,
) -> list[ServiceSpec]:
    """Router first; then counter, learner, evaluator, `actors` actors, and the API last.

    `slots` > 1: that many runs at once, each on a learner, an evaluator and `actors`
    actors of its own (ids `learner`, `learner1`, ...; actors numbered on), with the
    one counter, which serves every run; the API's scheduler starts queued runs on
    whichever are free.

    `endpoint` is where services connect; `listen` where the router listens (the same
    by default; docker-compose listens on all interfaces and connects by host name).
    `api` is the API's HTTP address (None: no API). When the router listens on all
    interfaces (containers), so does the API, which then needs MACB_API_TOKEN.
    `group_size` > 1: the API starts up to that many queued lockstep runs of one
    experiment that can share a group as one run group (a slot serves a group).
    `secrets`: a folder `macb certs` wrote; each service then signs in as its own id
    (MACB_ZENOH_USER, the router as `router`) with its files there (docs/deploy.md).
    """

    def signed_in(user: str, env: tuple[tuple[str, str], ...]) -> tuple[tuple[str, str], ...]:
        if secrets is None:
            return env
        return (*env, ("MACB_ZENOH_SECRETS", secrets), ("MACB_ZENOH_USER", user))

    env = (("MACB_ZENOH_CONNECT", endpoint), *THREAD_ENV.items())
    router_args = ("router", "--listen", listen or endpoint)
    plan = [ServiceSpec("router", router_args, signed_in("router", tuple(THREAD_ENV.items())))]
    counter_args = ("counter", "--id", "counter", "--data-dir", data_dir)
    plan.append(ServiceSpec("counter", counter_args, signed_in("counter", env)))
    for slot in range(slots):
        for role in ("learner", "evaluator"):
            sid = role if slot == 0 else f"{role}{slot}"
            args = (role, "--id", sid, "--data-dir", data_dir)
            plan.append(ServiceSpec(sid, args, signed_in(sid, env)))
    for r in range(actors * slots):
        args = ("actor", "--id", f"actor{r}", "--data-dir", data_dir)
        plan.append(ServiceSpec(f"actor{r}", args, signed_in(f"actor{r}", env)))
    if api is not None:
        if listen and listen.split("/", 1)[-1].startswith("0.0.0.0:"):
            api = "0.0.0.0:" + api.rsplit(":", 1)[1]
        api_args = ("api", "--id", "api", "--listen-http", api, "--data-dir", data_dir)
        api_env = (*env, ("MACB_API_GROUP_SIZE", str(group_size))) if group_size > 1 else env
        plan.append(ServiceSpec("api", api_args, signed_in("api", api_env)))
    return plan


def slot_plan(slot: str, actors: int, data_dir: str, signed_in: bool) -> list[ServiceSpec]:
    """One worker slot as `macb serve slot --id SLOT` runs it: a learner, an evaluator and
    `actors` actors (`learner-SLOT`, `evaluator-SLOT`, `actor-SLOT`, `actor-SLOT-1`, ...),
    connecting where MACB_ZENOH_CONNECT says. The Slurm cluster job starts one per task on
    every node (cli/slurm_cluster.py); `signed_in`: each signs in as its id (a secure bus,
    MACB_ZENOH_SECRETS set)."""
    ids = [f"learner-{slot}", f"evaluator-{slot}"]
    ids += [f"actor-{slot}" + (f"-{r}" if r else "") for r in range(actors)]
    plan = []
    for sid in ids:
        env = (*THREAD_ENV.items(), *((("MACB_ZENOH_USER", sid),) if signed_in else ()))
        role = sid.split("-", 1)[0]
        plan.append(ServiceSpec(sid, (role, "--id", sid, "--data-dir", data_dir), env))
    return plan


def _pump(name: str, stream: IO[bytes], log_file: IO[bytes], echo: bool) -> None:
    """Copy a child's output to its log file and, prefixed with its name, to our stdout."""
    prefix = f"{name:>10} | ".encode()
    for line in iter(stream.readline, b""):
        log_file.write(line)
        log_file.flush()
        if echo:
            sys.stdout.buffer.write(prefix + line)
            sys.stdout.buffer.flush()


_HANDED: set[int] = set()  # ports free_port gave this process


def _ephemeral_range() -> tuple[int, int]:
    """The ports the kernel hands out as the local end of outgoing connections."""
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999  # (Linux's default)


def free_port(low: int = 20000) -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now, for a process about to
    listen on it (tests and benchmarks). The port is released before that process binds
    it, so it is drawn below the kernel's ephemeral range (the ports outgoing
    connections take meanwhile: the bus and HTTP clients make many), each at most once
    per process; the kernel's choice only if that range leaves no room."""
    import random

    first, _ = _ephemeral_range()
    candidates = [p for p in range(low, first) if p not in _HANDED]
    random.shuffle(candidates)
    for port in candidates[:200]:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _HANDED.add(port)
        return port
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PortInUse(RuntimeError):
    """A port the cluster would listen on is taken (or cannot be listened on): nothing
    was started."""


class DidNotListen(RuntimeError):
    """Our child ended before its port answered (another process may hold the port)."""


def host_port(address: str) -> tuple[str, int]:
    """HOST and PORT of a bus endpoint (`tcp/HOST:PORT`) or an HTTP address (`HOST:PORT`);
    ValueError, naming it, if it has no host or no port in 1-65535 (the resolver would
    take 70000 for 4464)."""
    host, _, port = address.split("/", 1)[-1].rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"{address!r} is not HOST:PORT with a port from 1 to 65535")
    return host.strip("[]"), int(port)


def listen_address(spec: ServiceSpec) -> tuple[str, int] | None:
    """Where the service of `spec` listens: the router's --listen, the API's
    --listen-http; None for the others."""
    for flag in ("--listen", "--listen-http"):
        if flag in spec.args:
            return host_port(spec.args[spec.args.index(flag) + 1])
    return None


def check_port_free(host: str, port: int) -> None:
    """Raise PortInUse unless a server could listen on HOST:PORT now. Probed by binding
    with SO_REUSEADDR: a listener there (on that address or on all of them) refuses it,
    connections an earlier cluster left in TIME_WAIT do not."""
    where = f"port {port} on {host}"
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (OSError, UnicodeError) as err:
        raise PortInUse(f"{where}: cannot resolve {host!r} ({err})") from None
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
            return
        except OSError as err:
            if err.errno != errno.EADDRINUSE:
                raise PortInUse(f"cannot listen on {where}: {err.strerror}") from None
    with socket.socket(family, kind, proto) as s:
        s.settimeout(1.0)
        listens = s.connect_ex(addr) == 0
    raise PortInUse(
        f"{where} is in use"
        + (": something listens on it" if listens else "")
        + " (another `macb up`, docker compose, another user's job?); stop it, or "
        "choose another port (--endpoint, --api-port)"
    )


def check_ports(plan: list[ServiceSpec]) -> None:
    """Raise PortInUse, naming every taken port, unless each port the plan's services
    listen on is free."""
    taken = []
    for spec in plan:
        if (address := listen_address(spec)) is not None:
            try:
                check_port_free(*address)
            except PortInUse as err:
                taken.append(f"{spec.name}: {err}")
    if taken:
        raise PortInUse("; ".join(taken))


def wait_port(endpoint: str, timeout: float = 20.0, proc: procs.Child | None = None) -> None:
    """Until something listens at `endpoint` (TimeoutError after `timeout`). With `proc`
    (the child that is to listen there): DidNotListen once it has ended, also just after
    the port answered, since then another process answered."""
    host, port = host_port(endpoint)

    def ended() -> None:
        if proc is not None and proc.poll() is not None:
            raise DidNotListen(
                f"the process to listen on {endpoint} ended (exit code {proc.returncode}) "
                "before it listened"
            )

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ended()
        with socket.socket() as s:
            if s.connect_ex((host, port)) == 0:
                ended()
                return
        time.sleep(0.05)
    raise TimeoutError(f"router did not listen on {endpoint}")


class Cluster:
    """Starts the plan's processes, restarts those that die (`supervise`), and
    `stop()` ends every one of them by PID."""

    def __init__(self, plan: list[ServiceSpec], log_dir: Path, echo: bool = True) -> None:
        self.plan = plan
        self.log_dir = Path(log_dir)
        self.echo = echo
        self.procs: dict[str, procs.Child] = {}
        self._threads: list[threading.Thread] = []
        self.restarts: collections.Counter[str] = collections.Counter()
        self._deaths: dict[str, collections.deque[float]] = collections.defaultdict(
            collections.deque
        )
        self._restart_at: dict[str, float] = {}
        self._stopping = False

    def start(self) -> None:
        """Every service of the plan, router first (back once it listens). Raises
        PortInUse, with nothing started, if a port the plan listens on is taken."""
        check_ports(self.plan)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        for spec in self.plan:
            self._spawn(spec)
        self._write_state()

    def _spawn(self, spec: ServiceSpec) -> None:
        """Start one service (a restart: its port checked free first); it dies with us."""
        if self.restarts[spec.name] and (address := listen_address(spec)) is not None:
            check_port_free(*address)
        env = {
            **os.environ,
            "PYTHONUNBUFFERED": "1",
            **dict(spec.env),
            "MACB_RESTARTS": str(self.restarts[spec.name]),
            **procs.parent_env(),
        }
        # In a session of its own: our signal handler, not the terminal, ends it.
        proc = forkserver.start_cli(["serve", *spec.args], env, pipe=True)
        self.procs[spec.name] = proc
        log_file = (self.log_dir / f"{spec.name}.log").open("ab")
        t = threading.Thread(
            target=_pump, args=(spec.name, proc.stdout, log_file, self.echo), daemon=True
        )
        t.start()
        self._threads.append(t)
        if spec.name == "router":
            wait_port(spec.args[spec.args.index("--listen") + 1], proc=proc)

    def _write_state(self) -> None:
        state = {
            name: {"pid": p.pid, "restarts": self.restarts[name], "alive": p.poll() is None}
            for name, p in self.procs.items()
        }
        path = self.log_dir.parent / "cluster.json"
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(state, indent=2) + "\n")
        os.replace(tmp, path)

    def supervise(self, now: float | None = None) -> str | None:
        """Restart dead children (after their backoff); the name of one that keeps dying
        (RESTART_LIMIT deaths in RESTART_WINDOW_S), which is not restarted, else None."""
        if self._stopping:
            return None
        now = time.monotonic() if now is None else now
        for spec in self.plan:
            p = self.procs.get(spec.name)
            if p is None or p.poll() is None:
                continue
            if spec.name not in self._restart_at:
                deaths = self._deaths[spec.name]
                deaths.append(now)
                while deaths and now - deaths[0] > RESTART_WINDOW_S:
                    deaths.popleft()
                if len(deaths) >= RESTART_LIMIT:
                    print(
                        f"{spec.name} died {len(deaths)} times within "
                        f"{RESTART_WINDOW_S:.0f} s (exit code {p.returncode}): giving it up",
                        file=sys.stderr,
                    )
                    self._write_state()
                    return spec.name
                delay = min(BACKOFF_S[1], BACKOFF_S[0] * 2 ** (len(deaths) - 1))
                self._restart_at[spec.name] = now + delay
                print(
                    f"{spec.name} died (exit code {p.returncode}); restarting it in "
                    f"{delay:g} s (restart {self.restarts[spec.name] + 1})",
                    file=sys.stderr,
                )
                self._write_state()
            elif now >= self._restart_at[spec.name]:
                del self._restart_at[spec.name]
                self.restarts[spec.name] += 1
                try:
                    self._spawn(spec)
                except (OSError, TimeoutError, PortInUse, DidNotListen) as err:
                    print(f"restarting {spec.name} failed: {err}", file=sys.stderr)
                self._write_state()
        return None

    def dead(self) -> list[str]:
        return [name for name, p in self.procs.items() if p.poll() is not None]

    def stop(self, grace: float = 15.0) -> None:
        self._stopping = True
        # Services first, router last, so they can flush over a live bus.
        procs.end_all([p for n, p in self.procs.items() if n != "router"], grace)
        router = self.procs.get("router")
        if router:
            procs.end(router, 5.0)
        forkserver.close_shared()
        if self.procs:
            self._write_state()
