"""A fork server for `macb` commands, `macb serve` foremost: one process loads torch,
numpy, the environments and Zenoh once, and each service is forked from it, instead of
a fresh interpreter loading them again for every service and every restart (most of
what starting a service costs, on two cores that the running services share).

`macb up`'s supervisor starts its services through it, and the tests their clusters and
`macb` commands (tests/harness.py). A forked command is the same program as `python -m
cli ARGS`: its own session, environment, working folder and output, its arguments as
its process title (`ps`, `pgrep -f` and the PID checks in shared/procs.py see `... -m
cli serve ROLE ...`), and our own modules imported after the fork, so whatever they read
from the environment as they load is its own. Only libraries that read nothing of ours
as they load are preloaded, and a command whose environment differs from the server's
in more than `_own` variables (thread counts and PYTHONPATH, say, are read as a library
loads) is started as its own interpreter instead.

The client is the commands' parent, as with `subprocess.Popen`: it makes itself a child
subreaper (Linux prctl), the server forks an intermediate that forks the command and
exits, and the command, re-parented to the client, is waited for with `os.waitpid`, so
exit codes, signals and PIDs behave as for a `Popen`'s child (`Forked`). The server runs
single-threaded and holds no thread pool (one BLAS/OpenMP thread, nothing run), so a
fork from it is safe; it dies with its client. Where the prctl is missing (not Linux)
the client starts interpreters as before. MACB_FORK_SERVER=0 turns it off.

The client is a subreaper only while a command is being started (`subreaping`), so the
orphans of what it starts go to init as before, not to it as zombies. The server dies
with the client's thread that started it (PR_SET_PDEATHSIG): `macb up` and the tests
start it from their main thread. What a forked command shares with its server, unlike
a fresh interpreter: the string hash seed and the room its title may use (the server's
arguments and environment); what the preloaded libraries print as they load is in no
command's output (the server's goes to /dev/null).
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import importlib
import io
import json
import os
import runpy
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO, Any

from shared import procs

# What the server loads before it forks anything: the libraries every service loads,
# none of them reading a variable of ours as it loads.
PRELOAD = (
    "numpy",
    "torch",
    "gymnasium",
    "pettingzoo",
    "mpe2",
    "zenoh",
    "msgpack",
    "yaml",
    "pydantic",
    "pydantic_settings",
    "setproctitle",
)
PR_SET_CHILD_SUBREAPER, PR_GET_CHILD_SUBREAPER = 36, 37  # linux/prctl.h
REPLY_TIMEOUT_S = 120.0  # the server's first reply waits for its preload


def _own(name: str) -> bool:
    """A variable a forked service may have apart from its server: ours (read by our
    code when it runs, never by a library as it loads), PYTHONUNBUFFERED (which `become`
    applies itself) and pytest's PYTEST_* (the test of the moment)."""
    return name.startswith(("MACB_", "PYTEST_")) or name == "PYTHONUNBUFFERED"


def _libc() -> ctypes.CDLL:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl  # noqa: B018 (not Linux: no prctl in the C library)
    except (OSError, AttributeError) as err:
        raise OSError(f"no child subreaper here: {err}") from err
    return libc


def subreaper() -> bool:
    """Whether this process is a child subreaper now."""
    flag = ctypes.c_int(0)
    if _libc().prctl(PR_GET_CHILD_SUBREAPER, ctypes.byref(flag), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_GET_CHILD_SUBREAPER) failed")
    return bool(flag.value)


def set_subreaper(on: bool) -> None:
    """Make this process the parent of the orphans among its descendants, or stop;
    OSError where the kernel cannot."""
    if _libc().prctl(PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER) failed")


@contextlib.contextmanager
def subreaping() -> Iterator[None]:
    """A child subreaper for the time of one start, so that the command the server forks
    is re-parented to us, and only it: an orphan of ours at any other time goes to init,
    which reaps it, not to us, who would not (a zombie kept until we exit)."""
    before = subreaper()
    set_subreaper(True)
    try:
        yield
    finally:
        set_subreaper(before)


class Forked:
    """A service the server forked, handled as the `subprocess.Popen` it stands in for
    (`pid`, `args`, `returncode`, `stdout`, `poll`, `wait`, `send_signal`, `terminate`,
    `kill`). This process is its parent (the subreaper), so it is waited for here, and
    its PID is not reused before that."""

    def __init__(self, pid: int, args: list[str], stdout: IO[bytes] | None = None) -> None:
        self.pid = pid
        self.args = args
        self.stdout = stdout
        self.returncode: int | None = None
        self._lock = threading.Lock()

    def poll(self) -> int | None:
        with self._lock:
            if self.returncode is None:
                try:
                    pid, status = os.waitpid(self.pid, os.WNOHANG)
                except ChildProcessError:  # reaped by someone else: its code is lost
                    pid, status = self.pid, 255 << 8
                if pid:
                    self.returncode = os.waitstatus_to_exitcode(status)
            return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        pause = 0.001
        while (code := self.poll()) is None:
            if deadline is not None and time.monotonic() >= deadline:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
            time.sleep(pause)
            pause = min(pause * 2, 0.05)
        return code

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:  # (once reaped, its PID may be another process's)
            procs.send(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class ForkServer:
    """The client's end: starts the server (its environment `env`, the one its services
    must share apart from `MACB_*`), then `start` forks services from it."""

    def __init__(self, env: Mapping[str, str]) -> None:
        with subreaping():  # here, only to learn that it can be had
            pass
        self.env = {k: v for k, v in env.items() if not _own(k)}  # what `serves` compares
        self.failed: str | None = None  # why it forks nothing more
        self._lock = threading.Lock()
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "cli.forkserver", str(theirs.fileno())],
                env={**self.env, **procs.parent_env()},
                pass_fds=[theirs.fileno()],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        finally:
            theirs.close()
        self.sock = mine
        self.sock.settimeout(REPLY_TIMEOUT_S)

    def serves(self, env: Mapping[str, str]) -> bool:
        """Whether a service of environment `env` may be forked from this server."""
        if self.failed is not None or self.proc.poll() is not None:
            return False
        return {k: v for k, v in env.items() if not _own(k)} == self.env

    def start(
        self,
        args: list[str],
        env: Mapping[str, str],
        cwd: Path | str | None = None,
        log: Path | None = None,
        pipe: bool = False,
    ) -> Forked:
        """`python -m cli ARGS`, forked: output appended to `log`, readable from
        `.stdout` with `pipe`, else dropped. OSError if the server cannot fork it."""
        read = None
        if pipe:
            read, out = os.pipe()
        elif log is not None:
            out = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        else:
            out = os.open(os.devnull, os.O_WRONLY)
        try:
            proc = self.start_fds(args, env, cwd, out)
        except OSError:
            if read is not None:
                os.close(read)
            raise
        finally:
            os.close(out)
        proc.stdout = os.fdopen(read, "rb") if read is not None else None
        return proc

    def start_fds(
        self,
        args: list[str],
        env: Mapping[str, str],
        cwd: Path | str | None,
        stdout: int,
        stderr: int | None = None,
    ) -> Forked:
        """`python -m cli ARGS`, forked, writing to the descriptors `stdout` and `stderr`
        (None: stdout's), which stay the caller's to close. OSError if it cannot."""
        request = {"args": list(args), "env": dict(env), "cwd": str(cwd or os.getcwd())}
        fds = [stdout] if stderr is None else [stdout, stderr]
        with self._lock:
            if self.failed is not None:
                raise OSError(f"the fork server is gone: {self.failed}")
            try:
                with subreaping():  # until the reply: by then the command is our child
                    socket.send_fds(self.sock, [json.dumps(request).encode()], fds)
                    reply = json.loads(self.sock.recv(1 << 16) or b'{"error": "it ended"}')
            except (OSError, ValueError) as err:
                reply = {"error": f"{type(err).__name__}: {err}"}
            if "pid" not in reply:
                # A reply late or lost: nothing more is asked of it (a late one would be
                # taken for the next command's), it is ended, and the caller (and every
                # caller after it: `serves` says no) starts an interpreter.
                self.failed = str(reply.get("error"))
                print(f"the fork server failed ({self.failed}): each command loads its own",
                      file=sys.stderr)  # fmt: skip
                self.close()
                raise OSError(f"the fork server did not start {args}: {self.failed}")
        return Forked(int(reply["pid"]), [sys.executable, "-m", "cli", *args])

    def close(self) -> None:
        """End the server (its services go on: each is in a session of its own)."""
        with contextlib.suppress(OSError):
            self.sock.close()
        procs.end(self.proc, 5.0)


_SHARED: ForkServer | None = None
_SHARED_LOCK = threading.Lock()
_REFUSED: str | None = None  # why this process has no server (said once)


def _shared_server() -> ForkServer | None:
    """This process's one server, started with this process's environment (our own
    variables left out); None where a child subreaper cannot be had."""
    global _SHARED, _REFUSED
    with _SHARED_LOCK:
        if _SHARED is None and _REFUSED is None:
            try:
                _SHARED = ForkServer({k: v for k, v in os.environ.items() if not _own(k)})
            except OSError as err:
                _REFUSED = str(err)
                print(f"no fork server ({err}): each service loads its own", file=sys.stderr)
        return _SHARED


def server_for(env: Mapping[str, str]) -> ForkServer | None:
    """This process's server, if a command of environment `env` may be forked from it
    (module doc); None where it may not, MACB_FORK_SERVER=0 in `env` included."""
    forks = env.get("MACB_FORK_SERVER", "1").strip().lower() not in ("0", "off", "false", "no")
    server = _shared_server() if forks else None
    return server if server is not None and server.serves(env) else None


def start_cli(
    args: list[str],
    env: Mapping[str, str],
    *,
    cwd: Path | None = None,
    log: Path | None = None,
    pipe: bool = False,
) -> subprocess.Popen[bytes] | Forked:
    """`python -m cli ARGS` as `procs.start` starts it (a session of its own, output to
    `log`, or to `.stdout` with `pipe`), forked from this process's server when it may
    be (`server_for`)."""
    if (server := server_for(env)) is not None:
        with contextlib.suppress(OSError):  # (the server failed: an interpreter instead)
            return server.start(args, env, cwd, log, pipe)
    return procs.start([sys.executable, "-m", "cli", *args], log=log, pipe=pipe, env=env, cwd=cwd)


def close_shared() -> None:
    """End this process's server, if it has one (`macb up` as it stops)."""
    global _SHARED
    with _SHARED_LOCK:
        if _SHARED is not None:
            _SHARED.close()
            _SHARED = None


# ------------------------------------------------------------------ the server's side
def serve(fd: int) -> dict[str, Any] | None:
    """Fork a service per request on socket `fd` until the client goes. Returns None in
    the server when it goes, and the request in each forked service (which then
    `become`s it), so the service unwinds out of here as a program's main returns."""
    procs.die_with_env_parent()
    server_cwd = os.getcwd()
    sock = socket.socket(fileno=fd)
    for name in PRELOAD:
        importlib.import_module(name)
    import setproctitle

    # Taken over now, while the environment is still the one the kernel laid out after
    # the arguments: the services' titles may then use that room too.
    setproctitle.setproctitle(setproctitle.getproctitle())
    gc.freeze()  # the preloaded objects: never collected, so their pages stay shared
    while True:
        try:
            msg, fds, _, _ = socket.recv_fds(sock, 1 << 20, 2)
        except OSError:
            return None
        if not msg:
            return None
        pipe: tuple[int, int] | None = None
        try:
            request = json.loads(msg)
            pipe = read, write = os.pipe()
            sys.stdout.flush()  # (nothing of ours is written twice by the fork)
            sys.stderr.flush()
            middle = os.fork()
        except (OSError, ValueError) as err:
            for f in [*fds, *(pipe or ())]:
                os.close(f)
            sock.send(json.dumps({"error": f"{type(err).__name__}: {err}"}).encode())
            continue
        if middle == 0:  # the intermediate: forks the command and leaves it orphaned
            os.close(read)
            me = os.getpid()
            try:
                pid = os.fork()
            except OSError:
                os._exit(1)  # (nothing written: the server replies with an error)
            if pid == 0:  # the command: a session of its own before its PID is known
                os.setsid()
                os.write(write, str(os.getpid()).encode())
                os.close(write)
                sock.close()
                return {**request, "fds": fds, "middle": me, "server_cwd": server_cwd}
            os._exit(0)
        os.close(write)
        for f in fds:
            os.close(f)
        with os.fdopen(read, "rb") as r:
            pid_text = r.read()  # (to its end: the command and the intermediate closed it)
        os.waitpid(middle, 0)  # gone: the command is the client's child now
        reply = {"pid": int(pid_text)} if pid_text else {"error": "the fork failed"}
        sock.send(json.dumps(reply).encode())


def _stream(fd: int, unbuffered: bool, errors: str, line: bool) -> io.TextIOWrapper:
    raw = io.FileIO(fd, "w", closefd=False)
    binary: io.RawIOBase | io.BufferedWriter = raw if unbuffered else io.BufferedWriter(raw)
    return io.TextIOWrapper(
        binary,  # type: ignore[arg-type]
        encoding="utf-8",
        errors=errors,
        line_buffering=line,
        write_through=unbuffered,
    )


def become(request: dict[str, Any]) -> int:
    """Turn this forked process into `python -m cli ARGS` as a fresh start would be."""
    while os.getppid() == request["middle"]:  # re-parented to the client first
        time.sleep(0.0005)
    for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD, signal.SIGUSR1, signal.SIGUSR2):
        signal.signal(sig, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    out, err = request["fds"][0], request["fds"][-1]  # (one descriptor: both)
    os.dup2(out, 1)
    os.dup2(err, 2)
    for fd in set(request["fds"]) - {1, 2}:
        os.close(fd)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    unbuffered = bool(os.environ.get("PYTHONUNBUFFERED"))
    sys.stdout = _stream(1, unbuffered, "strict", False)
    sys.stderr = _stream(2, True, "backslashreplace", True)
    sys.stdin = open(0, encoding="utf-8", closefd=False)  # noqa: SIM115
    args = list(request["args"])
    if sys.path and sys.path[0] == request["server_cwd"]:
        sys.path[0] = request["cwd"]  # where `-m` would have put it
    import setproctitle

    setproctitle.setproctitle(" ".join([sys.executable, "-m", "cli", *args]))
    sys.argv = [str(Path(__file__).with_name("__main__.py")), *args]
    # As `python -m cli` runs: cli/__main__.py as __main__, its SystemExit the exit code.
    runpy.run_module("cli", run_name="__main__", alter_sys=True)
    return 0


def main() -> int:
    request = serve(int(sys.argv[1]))
    return 0 if request is None else become(request)


if __name__ == "__main__":
    sys.exit(main())
