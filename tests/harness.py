"""What the tests share: the `macb` command as a subprocess, the cluster of real
processes on loopback, the exactness check of a finished run, and the small configs.

`Cluster` is the one cluster harness. Its processes listen on 127.0.0.1 ports of their
own, each logs to its own file, and `stop()` (or leaving its `with` block) ends every
one by PID (`shared.procs`, as `macb up` and the benchmarks do) and fails if any
outlived it. It runs either way a test needs:

- one by one, `macb serve ROLE` per process (`router`, `services`, `api`, `start`), so
  a test can kill, pause or restart any one of them;
- supervised, the whole cluster as a user runs it (`up`: `macb up`, which restarts
  what dies).

With `secrets` (a `macb certs` folder) the endpoints are TLS and every process signs
in as its own user.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import selectors
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from cli import forkserver
from cli.supervisor import THREAD_ENV, free_port, wait_port
from shared import procs

ROOT = Path(__file__).resolve().parent.parent

# ---------------------------------------------------------------- small configs
NETS = {"hidden": [32, 32], "batch_size": 16, "eval_episodes": 2}  # small and quick
# A run of a few seconds: 12 episodes of speaker_listener, a point every 4.
TINY = {
    "task": "speaker_listener",
    "algo": "cen-maddpg",
    "explore": "cen-macb",
    "k": 64,
    "episodes": 12,
    "eval_every": 4,
    **NETS,
}
# Long enough for every service's accounts to mean something: 30 episodes (600
# transitions), a point every 5, networks wide enough for the learner to take its time.
SMALL = {
    **TINY,
    "episodes": 30,
    "eval_every": 5,
    "eval_episodes": 3,
    "hidden": [64, 64],
    "batch_size": 32,
}


def write_config(path: Path, config: dict) -> Path:
    """`config` as the YAML file a user gives `macb run` or `macb up --run`."""
    import yaml

    path.write_text(yaml.safe_dump(config))
    return path


# ---------------------------------------------------------------- the command
def wait_for(predicate, timeout: float = 30.0, interval: float = 0.05, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"timed out waiting for {what}")


def _environ(env: dict[str, str | None] | None) -> dict[str, str]:
    """This process's variables with `env` over them (None unsets one)."""
    out = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    return {k: v for k, v in out.items() if v is not None}


def macb(
    *args: str,
    env: dict[str, str | None] | None = None,
    timeout: float = 300,
    check: bool = False,
) -> subprocess.CompletedProcess:
    """`macb ARGS` run from the checkout to its end, its output captured as text.
    `env`: variables over this process's (None unsets one); `check`: fail, showing
    the end of its stderr, unless it exits 0. Forked from this process's fork server
    (cli/forkserver.py) when it may be: the command's code is the same, without
    loading torch again."""
    environ = _environ(env)
    server = forkserver.server_for(environ)
    proc = None
    if server is not None:
        with contextlib.suppress(OSError):  # (the server failed: an interpreter instead)
            proc = _run_forked(server, list(args), environ, timeout)
    if proc is None:
        proc = subprocess.run(
            [sys.executable, "-m", "cli", *args],
            cwd=ROOT,
            env=environ,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def _run_forked(server, args: list[str], env: dict[str, str], timeout: float):
    """`subprocess.run(..., capture_output=True, text=True, timeout=...)` of a forked
    `macb ARGS`: both outputs read to their end, universal newlines as text=True gives;
    on a timeout or an interruption the command is killed and reaped, as there.
    OSError if the server cannot start it."""
    pipes = [os.pipe(), os.pipe()]
    try:
        p = server.start_fds(args, env, ROOT, pipes[0][1], pipes[1][1])
    except OSError:
        for r, _ in pipes:
            os.close(r)
        raise
    finally:
        for _, w in pipes:
            os.close(w)
    chunks: dict[int, list[bytes]] = {r: [] for r, _ in pipes}
    deadline = time.monotonic() + timeout
    with selectors.DefaultSelector() as sel:
        for r, _ in pipes:
            sel.register(r, selectors.EVENT_READ)
        try:
            while sel.get_map():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise subprocess.TimeoutExpired(p.args, timeout)
                for key, _ in sel.select(min(left, 1.0)):
                    data = os.read(key.fd, 1 << 16)
                    if data:
                        chunks[key.fd].append(data)
                    else:
                        sel.unregister(key.fd)
                        os.close(key.fd)
            code = p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except BaseException:
            p.kill()
            p.wait()
            raise
        finally:
            for fd in list(sel.get_map()):
                sel.unregister(fd)
                os.close(fd)
    out, err = (io.TextIOWrapper(io.BytesIO(b"".join(chunks[r]))).read() for r, _ in pipes)
    return subprocess.CompletedProcess(p.args, code, out, err)


def spawn(*args: str, log: Path | None = None, env: dict | None = None) -> procs.Child:
    """`macb ARGS` started in a session of its own (a test ends it, and whatever it
    started, by PID), its output appended to `log` (or dropped); forked when it may be."""
    return forkserver.start_cli(list(args), _environ(env), cwd=ROOT, log=log)


def parents() -> dict[int, int]:
    """Every live process's parent (PID -> PID), from /proc; zombies left out."""
    found: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if fields[0] != "Z":
            found[int(stat.parent.name)] = int(fields[1])
    return found


def processes_with(marker: str) -> list[str]:
    out = subprocess.run(["pgrep", "-af", marker], capture_output=True, text=True).stdout
    return [line for line in out.splitlines() if "pgrep" not in line]


def cluster_processes(endpoint: str, data: Path) -> list[str]:
    """`macb serve` processes of one cluster (its router by port, services by data dir)."""
    lines = processes_with(endpoint.split(":")[-1]) + processes_with(str(data))
    return sorted({line for line in lines if " serve " in line})


# ---------------------------------------------------------------- the secure bus
def as_user(secrets: Path, user: str) -> dict[str, str]:
    """The variables that sign a process in as `user`."""
    return {"MACB_ZENOH_SECRETS": str(secrets), "MACB_ZENOH_USER": user}


def session(secrets: Path, user: str, endpoint: str, **override):
    """A bus session of this test's, signed in as `user`."""
    from shared.net.bus import Bus
    from shared.net.security import Security

    sec = Security.from_env({**as_user(secrets, user), **override})
    return Bus([endpoint], security=sec)


def router_stats(bus, router: str = "router") -> dict:
    """The router's answer on macb/router/ID (it declares it just after it listens)."""
    from shared.net import bus as keys

    replies = wait_for(
        lambda: bus.get(keys.k_router(router), timeout=2.0), timeout=10, what=f"{router} stats"
    )
    return json.loads(replies[0])


# ---------------------------------------------------------------- the cluster
SERVICE_ROLES = ("counter", "learner", "evaluator")


class Cluster:
    """Real processes on loopback ports of their own, ended by PID (see the module).

    `tmp`: the folder of the logs (NAME.log); `data`, under it, is the services' and
    the API's data dir. `env`: variables for every process started."""

    def __init__(
        self, tmp: Path, endpoint: str | None = None, *, env=None, secrets: Path | None = None
    ) -> None:
        self.tmp = Path(tmp)
        self.data = self.tmp / "data"
        self.secrets = secrets
        self.endpoint = endpoint or f"{'tls' if secrets else 'tcp'}/127.0.0.1:{free_port()}"
        self.url = f"http://127.0.0.1:{free_port()}"  # the API's, when there is one
        self.env: dict[str, str] = dict(env or {})
        self.procs: dict[str, procs.Child] = {}
        self.seen: set[int] = set()  # every PID of the cluster, macb up's children too
        self.api_name: str | None = None  # the process /workers is asked of
        self.answering = 0  # workers that answer when the cluster is ready

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, failing, *exc) -> None:
        try:
            self.stop()
        except BaseException:
            if failing is None:  # else the test's own failure is the one to see
                raise

    # ---------------------------------------------------------- one by one
    def start(self, name: str, *args: str, env=None, user: str | None = None):
        """`macb serve ARGS` as process `name`, one torch/BLAS thread, on this cluster's
        endpoint; signed in as `user` (default: `name`) when the cluster is secure."""
        signed_in = as_user(self.secrets, user or name) if self.secrets else {}
        env = {
            "MACB_ZENOH_CONNECT": self.endpoint,
            **THREAD_ENV,
            **self.env,
            **signed_in,
            **(env or {}),
        }
        p = forkserver.start_cli(
            ["serve", *args], _environ(env), cwd=ROOT, log=self.tmp / f"{name}.log"
        )
        self.procs[name] = p
        self.seen.add(p.pid)
        return p

    def router(self, name: str = "router", listen: str | None = None, connect=None) -> str:
        """A router listening on `listen` (default: the cluster's endpoint), peered with
        the router at `connect`; back once it listens."""
        listen = listen or self.endpoint
        self.start(name, "router", "--listen", listen, *(["--connect", connect] if connect else []))
        wait_port(listen)
        return listen

    def service(self, role: str, sid: str | None = None, *, name=None, connect=None, env=None):
        """`macb serve ROLE --id SID` on the data dir, as process `name` (default: the
        id; another name restarts the same service), through the router at `connect`."""
        sid = sid or role
        where = {"MACB_ZENOH_CONNECT": connect} if connect else {}
        args = (role, "--id", sid, "--data-dir", str(self.data))
        return self.start(name or sid, *args, env={**where, **(env or {})}, user=sid)

    def services(self, actors: int = 1, *, connect: dict[str, str] | None = None) -> None:
        """A counter, a learner, an evaluator and `actors` actors (actor0, ...); `connect`:
        service id -> the router it goes through, if not the cluster's."""
        connect = connect or {}
        for sid in (*SERVICE_ROLES, *(f"actor{r}" for r in range(actors))):
            self.service(sid.rstrip("0123456789"), sid, connect=connect.get(sid))

    def api(self, name: str = "api", *, env=None, answering: int | None = 5) -> None:
        """`macb serve api` on the cluster's URL and data dir; back once it answers and
        `answering` workers answer on /workers (itself among them; None: at once)."""
        listen = self.url.removeprefix("http://")
        self.start(name, "api", "--listen-http", listen, "--data-dir", str(self.data), env=env)
        self.api_name = name
        if answering is not None:
            self.answering = answering
            wait_for(self.ready, timeout=120, interval=0.2, what="the API and its services")

    # ---------------------------------------------------------- supervised
    def up(self, *args: str, answering: int | None = None) -> subprocess.Popen:
        """`macb up ARGS` on the cluster's endpoint, data dir and API port, as a user runs
        it (its output: up.log); with `answering`, back once that many workers answer."""
        port = self.url.rsplit(":", 1)[1]
        where = ("--endpoint", self.endpoint, "--data-dir", str(self.data), "--api-port", port)
        p = spawn("up", *where, *args, log=self.tmp / "up.log", env=self.env)
        self.procs["up"] = p
        self.seen.add(p.pid)
        self.api_name = "up"
        if answering is not None:
            self.answering = answering
            wait_for(self.ready, timeout=120, interval=0.3, what="macb up: API and services")
        return p

    def wait(self, timeout: float) -> tuple[int, str]:
        """`macb up`'s exit code and output, once it has ended by itself."""
        code = self.procs["up"].wait(timeout=timeout)
        return code, self.log("up")

    def pids(self) -> dict[str, int]:
        """`macb up`'s services by name, as its cluster.json has them now."""
        state = json.loads((self.data / "cluster.json").read_text())
        pids = {name: s["pid"] for name, s in state.items()}
        self.seen.update(pids.values())
        return pids

    def restarts(self) -> dict[str, int]:
        state = json.loads((self.data / "cluster.json").read_text())
        return {name: s["restarts"] for name, s in state.items()}

    # ---------------------------------------------------------- either way
    def pid(self, name: str) -> int:
        """A process of ours, or one of `macb up`'s services."""
        return self.procs[name].pid if name in self.procs else self.pids()[name]

    def kill(self, name: str, sig: int = signal.SIGKILL, timeout: float = 20) -> None:
        """Signal one process (SIGKILL unless told); one of ours is waited for."""
        if name not in self.procs:
            procs.send(self.pids()[name], sig)
        elif self.procs[name].poll() is None:
            os.kill(self.procs[name].pid, sig)
            try:
                self.procs[name].wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                # A service still up writes its threads' stacks to its log
                # (services.common.SHUTDOWN_STACKS_AFTER_S): the failure shows them.
                self.procs[name].kill()
                tail = "\n".join(self.log(name).splitlines()[-200:])
                raise AssertionError(
                    f"{name} still running {timeout:g} s after signal {sig}; its log's end:\n{tail}"
                ) from None

    def pause(self, *names: str, seconds: float) -> None:
        """SIGSTOP each process, then SIGCONT them all `seconds` later."""
        pids = [self.pid(name) for name in names]
        try:
            for pid in pids:
                procs.send(pid, signal.SIGSTOP)
            time.sleep(seconds)
        finally:
            for pid in pids:
                procs.send(pid, signal.SIGCONT)

    def kill_all(self) -> None:
        """SIGKILL `macb up` and every service: nothing is told, nothing flushes. Back
        once all are gone (their ports free: a `macb up` after this refuses taken ones)."""
        pids = self.pids()
        self.procs["up"].kill()
        self.procs["up"].wait()
        for pid in pids.values():
            procs.send(pid, signal.SIGKILL)
        wait_for(lambda: not any(procs.alive(p) for p in pids.values()), 30, what="the kill")

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")

    def report(self, lines: int = 40) -> None:
        """The end of each process's log, for a failed test's report."""
        for name in self.procs:
            text = self.log(name).splitlines()
            print(f"----- {name}.log (last {lines} of {len(text)} lines) -----")
            print("\n".join(text[-lines:]))

    def ready(self) -> bool:
        """The API answers, and `answering` workers on its /workers do."""
        import httpx

        if self.api_name is not None:
            assert self.procs[self.api_name].poll() is None, self.log(self.api_name)[-4000:]
        try:
            workers = httpx.get(f"{self.url}/workers", timeout=5).json()["workers"]
        except (httpx.HTTPError, ValueError, KeyError):
            return False
        return len([w for w in workers if w["answers"]]) >= self.answering

    def get(self, path: str) -> Any:
        """GET `path` of the API: its JSON, or None while the API is away or says no."""
        import httpx

        try:
            r = httpx.get(f"{self.url}{path}", timeout=5)
            return r.json() if r.status_code == 200 else None
        except (httpx.HTTPError, ValueError):
            return None  # the API itself may be restarting

    def points(self, run: str) -> int:
        """The run's stored points (-1 while the API does not say)."""
        row = self.get(f"/runs/{run}")
        return row["points"] if row else -1

    def ended(self, *runs: str) -> bool:
        """Every one of the runs has ended, as the API says."""
        states = [(self.get(f"/runs/{run}") or {}).get("status") for run in runs]
        return all(s not in (None, "queued", "running") for s in states)

    def finished(self, run: str) -> Finished:
        """The run's end as the API stored it, for `assert_exact`."""
        from shared.config import make_config

        record = self.get(f"/runs/{run}")
        assert record is not None
        page = self.get(f"/runs/{run}/metrics?limit=100000")
        assert page is not None
        tail = self.log(self.api_name)[-4000:] if self.api_name else ""
        return Finished(
            make_config(record["config"]),
            record["status"],
            record["assign"],
            record["services"],
            page["points"],
            said=(record["status"], record["reason"], tail),
            record=record,
        )

    def leftovers(self) -> list[str]:
        """`macb serve` processes of this cluster still running."""
        return cluster_processes(self.endpoint, self.data)

    def stop(self) -> None:
        """End every process by PID: SIGTERM, SIGKILL what is left after a grace (a
        minute for `macb up`, which ends its own); fail if any of the cluster's outlived it."""
        procs.end_all(self.procs.values(), 60 if "up" in self.procs else 10)
        if (self.data / "cluster.json").exists():
            self.pids()
        ours = {p.pid for p in self.procs.values()}  # waited for: their PIDs are free
        left = [pid for pid in self.seen - ours if procs.alive(pid) and self._mine(pid)]
        for pid in left:
            procs.send(pid, signal.SIGKILL)
        if left:
            pytest.fail(f"process(es) {left} outlived the cluster")

    def _mine(self, pid: int) -> bool:
        """A PID still this cluster's (not reused by another process since)."""
        return procs.names_one_of(pid, (str(self.data), self.endpoint.rsplit(":", 1)[1]))


@contextlib.contextmanager
def api_cluster(tmp: Path, api_env: dict[str, str] | None = None):
    """Router, counter, learner, evaluator, one actor and the API, all processes
    (`api_env`: more variables for the API's process)."""
    # A dead service that does not come back fails its run after this grace (30 s by
    # default): shorter here, where a learner may be killed for good.
    with Cluster(tmp, env={"MACB_PEER_GRACE_S": "8"}) as cluster:
        cluster.router()
        cluster.services(actors=1)
        cluster.api(env=api_env)
        yield cluster


def wait_services(bus, n: int, timeout: float = 60) -> list[dict]:
    """At least `n` services answer on the bus."""
    from shared.net.control import discover

    return wait_for(lambda: len(discover(bus)) >= n, timeout=timeout, what=f"{n} services")


# ---------------------------------------------------------------- exactness
@dataclass
class Finished:
    """A run at its end as the exactness check reads it: its status, its services'
    final reports (service id -> status) and its evaluation points, oldest first."""

    config: Any  # TrainConfig
    status: str
    assign: dict
    states: dict[str, dict]
    rows: list[dict]
    said: Any = None  # shown when a check fails
    record: dict | None = None  # the API's run, when read from the API

    @classmethod
    def of_watch(cls, watch, config) -> Finished:
        """A run watched on the bus (shared.net.control.RunWatch)."""
        rows = sorted(watch.rows, key=lambda r: r["episode"])
        state = watch.state()
        assign = watch.assign.to_wire()  # as the API's record shows it
        return cls(config, state, assign, watch.states, rows, said=(state, watch.states))

    @property
    def learner(self) -> dict:
        return self.states[self.assign["learner"]]

    @property
    def counter(self) -> dict:
        return self.states[self.assign["counter"]]


def assert_exact(run, config=None, *, faults: str | None = None) -> Finished:
    """A finished run is exact (docs/reliability.md): it completed, every collected
    transition was counted once and is in replay (counted == collected == ingested),
    updates == collected - warm-up (replay ratio 1) and each evaluation point is stored
    once. `run`: a RunWatch (with its `config`) or `Cluster.finished(run_id)`.

    With no fault the services' own accounts must add up too: the actors published
    every transition, a duplicate is only ever a batch an actor resent, the rows and
    the learner's diagnostics are in range. `faults`:
    - "lost": messages were lost in transit (a router restarted): a lost batch makes
      the batch after it a gap (refused, not counted) until the actor resends both
      (tests/test_protocol.py), so gaps may occur, each answered by a resend;
    - "restarted": processes were killed or paused and restarted: a new process's
      accounts start over, so the guarantee alone is checked."""
    run = run if isinstance(run, Finished) else Finished.of_watch(run, config)
    config = run.config
    assert run.status == "completed", run.said
    ran = config.episodes  # (a run its early_stop rule ended: the episode of its last row)
    last = max(run.rows, key=lambda r: r["episode"]) if run.rows else {}
    if last.get("stop_reason"):
        ran = last["episode"]
    collected = ran * config.episode_len
    learner, counter = run.learner, run.counter
    # The counter's final report (a completed run has it), not its last periodic stats,
    # which may come after it.
    assert counter["counted_transitions"] == collected, counter
    assert learner["ingested"] == collected, learner
    assert learner["updates"] == collected - config.learning_starts, learner
    assert learner["replay_ratio"] == 1.0, learner
    points = [r["episode"] for r in run.rows]
    assert points == list(range(config.eval_every, ran + 1, config.eval_every))
    if faults == "restarted":
        return run
    actors = [run.states[a] for a in run.assign["actors"]]
    assert sum(a["final_seq"] for a in actors) == collected, json.dumps(actors)
    # Duplicates are ignored (that is the guarantee); each one must be a batch an actor
    # resent, after a second with no ack moving (a learner stalled on a loaded machine
    # makes that happen), never a second delivery of one publication.
    resends = sum(a.get("resends", 0) for a in actors)
    assert counter["duplicates"] <= resends * config.episode_len, json.dumps([counter, actors])
    assert counter["gaps"] <= (resends if faults == "lost" else 0), json.dumps([counter, actors])
    for r in run.rows:
        assert 0.0 <= r["success_rate"] <= 1.0
        assert r["env_steps"] == r["episode"] * config.episode_len
        if config.counts and r["env_steps"] > config.learning_starts:
            # the counter's tables as of the tick that trained up to this point: it has
            # counted at least every transition trained on
            assert r["counted_transitions"] >= r["env_steps"], r
            assert r["table_size"] > 0 and 0.0 < r["count1_pct"] <= 100.0, r
        if r["env_steps"] > config.learning_starts + config.eval_every * config.episode_len:
            # what the bonus did on the rows sampled since the last point (every row of
            # such a point had updates since the point before)
            beta = config.beta if config.explore != "none" else 0.0
            assert 0.0 <= r["bonus_std"] <= beta and 0.0 <= r["sampled_count1_pct"] <= 100, r
            assert (0.0 < r["bonus_mean"] <= beta + 1e-6) or beta == 0.0, r
    if config.counts and config.interleave == "async":
        # bonuses priced per tick (all of its minibatches in one query), not per update
        # (lockstep: a tick is one step's one update)
        assert learner["bonus_rows_per_query"] >= 5 * config.batch_size, learner
        assert learner["bonus_queries"] * 5 <= learner["updates"], learner
        # (a query unanswered in time is priced again: a loaded machine's, not an error)
        assert learner["bonus_failures"] == 0, learner
        assert 0.0 < learner["bonus_wait_ms_per_update"] < 1e3, learner
    # The learner saw the evaluator's rows (what ends its contended updates) and
    # accounted for its time by phase. How many updates were contended is timing alone
    # (on a loaded machine every one of a short run can overlap an evaluation), so only
    # its range is checked; tests/test_batched_equivalence.py tests the marking.
    assert 0 < learner["eval_rows_seen"] <= len(points), learner
    assert 0 <= learner["contended_updates"] <= learner["updates"], learner
    assert learner["ms_per_update_update"] > 0.0, learner
    return run


def wait_final_counts(watch, config, timeout: float = 10) -> None:
    """The counter publishes its stats each second: wait for the final ones."""
    wait_for(
        lambda: (
            (watch.latest.get("counter") or {}).get("counted_transitions")
            == config.episodes * config.episode_len
        ),
        timeout=timeout,
        what="final counter stats",
    )


# ---------------------------------------------------------------- the API in process
def start_api(tmp_path: Path, router: str | None, **settings):
    """The API in this process (uvicorn on a free port) on a store under `tmp_path`;
    without a router, on a bus nothing answers."""
    from services.api.main import ApiServer, Settings

    connect = [router] if router else ["tcp/127.0.0.1:1"]  # nothing listens on port 1
    return ApiServer(
        Settings(port=0, data_dir=tmp_path / "api", connect=connect, **settings)
    ).start()


def post(client, body, **kw):
    return client.post("/experiments", json=body, **kw)


def row(episode: int, **extra) -> dict:
    """A metric row with the evaluator's fields."""
    from services.api.store import CSV_FIELDS

    base = {f: float(episode) for f in CSV_FIELDS}
    base.update(episode=episode, env_steps=episode * 20, success_rate=episode / 100)
    return {**base, **extra}
