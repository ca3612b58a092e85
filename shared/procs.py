"""Child processes started and ended by PID: the one way `macb up`'s supervisor, the
tests' harness and the benchmarks do it.

The machine may be shared (a campaign, other people's processes), so a child is never
looked for by name: each starts in a session (and process group) of its own, so a
terminal's Ctrl-C reaches only its parent and its group can be ended without touching
anyone else's; it is ended by its PID, SIGTERM first (services flush their snapshots
and checkpoints), SIGKILL once its grace is over. A PID that is not our child any more
is signalled only after checking, from its command line, that it is still one of ours.
Standard library only, so a benchmark can import this before it sets its thread
variables and loads numpy.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import IO, Protocol


class Child(Protocol):
    """A child process as this module handles it: a `subprocess.Popen`, or a service
    forked for this process (cli/forkserver.py's `Forked`), which this one waits for."""

    pid: int
    returncode: int | None
    stdout: IO[bytes] | None

    def poll(self) -> int | None: ...
    def wait(self, timeout: float | None = None) -> int: ...
    def send_signal(self, sig: int) -> None: ...
    def kill(self) -> None: ...


def start(
    argv: list[str],
    *,
    log: Path | None = None,
    pipe: bool = False,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
) -> subprocess.Popen[bytes]:
    """A child in a session of its own, stdin from /dev/null, stdout and stderr appended
    to `log`, or readable from `p.stdout` with `pipe`, else dropped. `env` None: this
    process's environment."""
    out: IO[bytes] | int = subprocess.DEVNULL
    if pipe:
        out = subprocess.PIPE
    elif log is not None:
        out = open(log, "ab")  # noqa: SIM115 (closed below: the child has its own copy)
    try:
        return subprocess.Popen(
            argv,
            cwd=cwd,
            env=None if env is None else dict(env),
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
    finally:
        if not isinstance(out, int):
            out.close()


def send(pid: int, sig: int) -> None:
    """Signal a PID; one that is gone already is no error."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)


def terminate(p: Child) -> None:
    """SIGTERM a child of ours still running (it flushes and exits)."""
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)


def reap(p: Child, deadline: float, group: bool = False) -> None:
    """Wait for a child until `deadline` (monotonic; at least a moment), then SIGKILL it,
    or with `group` its whole process group, and wait. The group id is the child's PID
    and still ours: a child is not reaped until wait() returns, so its PID cannot have
    been reused."""
    try:
        p.wait(timeout=max(0.1, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
        if group:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
        else:
            p.kill()
        p.wait()


def end(p: Child, grace: float, group: bool = False) -> None:
    """SIGTERM, `grace` seconds to exit, then SIGKILL (`reap`)."""
    if p.poll() is not None:
        return
    terminate(p)
    reap(p, time.monotonic() + grace, group)


def end_all(procs: Iterable[Child], grace: float, group: bool = False) -> None:
    """SIGTERM every one at once, then reap each by one deadline `grace` from now."""
    procs = list(procs)
    for p in procs:
        terminate(p)
    deadline = time.monotonic() + grace
    for p in procs:
        reap(p, deadline, group)


def cmdline(pid: int) -> list[str] | None:
    """A process's arguments, from /proc; None once it is gone."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return None
    return [a.decode(errors="replace") for a in raw.split(b"\0")]


def names_one_of(pid: int, marks: Iterable[str]) -> bool:
    """Whether the process runs one of ours: its command line contains one of `marks`
    (a data dir, a port), so a PID reused by someone else's process is left alone."""
    argv = cmdline(pid)
    return argv is not None and any(m in "\0".join(argv) for m in marks)


def alive(pid: int) -> bool:
    """The PID runs (a zombie, exited but not yet reaped, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent(parent: int, poll_s: float = 1.0) -> str:
    """End this process with SIGKILL as soon as `parent` (its parent's PID when it
    started) ends, however it ends: SIGKILL included, when no handler of the parent's
    can end its children. Returns how: "prctl" or "watchdog".

    On Linux the kernel does it (prctl PR_SET_PDEATHSIG): nothing in this process has to
    run for it, so it holds while this process is busy in a long C call, holds the GIL or
    is stopped, which a watchdog thread cannot promise. Elsewhere (no prctl) a daemon
    thread polls the parent's PID every `poll_s` seconds. The death signal fires when
    the thread that started this process ends, so start such children from the
    parent's main thread. A parent gone before this call is caught by the check after
    arming (this process is re-parented then)."""
    import ctypes

    how = "watchdog"
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0:
            how = "prctl"
    except (OSError, AttributeError):  # not Linux: no prctl in the C library
        pass
    if how == "watchdog":
        import threading

        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(poll_s)
            os.kill(os.getpid(), signal.SIGKILL)

        threading.Thread(target=watch, name="die-with-parent", daemon=True).start()
    if os.getppid() != parent:  # it ended before the signal was armed
        os.kill(os.getpid(), signal.SIGKILL)
    return how


PARENT_ENV = "MACB_PARENT_PID"  # (a field of shared.settings.Settings, read here itself)


def parent_env() -> dict[str, str]:
    """The variable that makes a `macb` command started with it die with this process
    (`die_with_env_parent`, first thing in `cli.main.main`). A variable and not
    `preexec_fn`: that runs between fork and exec, which is unsafe with threads (the
    supervisor pumps its children's output in threads)."""
    return {PARENT_ENV: str(os.getpid())}


def die_with_env_parent() -> str | None:
    """Die with the process MACB_PARENT_PID names (`die_with_parent`): how, or None when
    it is unset. The variable is taken out of this process's environment first, so a
    process this one starts does not take it for its own parent (its parent is not that
    PID, and it would kill itself at once). Raises ValueError if it is not a PID."""
    value = os.environ.pop(PARENT_ENV, None)
    if value is None or not value.strip():
        return None
    if not value.strip().isdigit() or int(value) < 1:
        raise ValueError(f"{PARENT_ENV} must be a process id, not {value!r}")
    return die_with_parent(int(value))
