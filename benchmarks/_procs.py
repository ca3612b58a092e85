"""The processes a benchmark starts: thread variables, process groups, CPU seconds, ending.

Benchmarks time real processes on a machine shared with other people's, so they must
neither leave one behind nor touch one that is not theirs: every child starts in a
process group of its own and is ended by its PID (SIGTERM, then SIGKILL to its group),
never by name, with `shared.procs` (as `macb up` and the tests). CPU seconds come from
/proc, which is where the cores went. Only the standard library, shared/procs.py and
cli/supervisor.py (stdlib only too), so a script can import this before it sets its
thread variables and loads numpy.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the project's packages, also without `pip install -e`
    sys.path.insert(0, str(ROOT))

from cli.supervisor import THREAD_ENV  # noqa: E402
from shared import procs  # noqa: E402
from shared.procs import cmdline  # noqa: E402

# The variables that set BLAS/OpenMP threads, as `macb up` gives every service.
THREAD_VARS = tuple(THREAD_ENV)


def pin_threads() -> None:
    """One BLAS/OpenMP thread in this process, as every service runs, unless the caller's
    environment says otherwise. Only works before numpy or torch is imported."""
    for var, value in THREAD_ENV.items():
        os.environ.setdefault(var, value)


def thread_env(one_thread: bool) -> dict[str, str]:
    """This environment for a child: with one BLAS thread (as `macb up`'s services), or
    with no thread variable at all (as from a plain shell, the libraries' defaults)."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    env["PYTHONUNBUFFERED"] = "1"
    if one_thread:
        env.update(THREAD_ENV)
    return env


def start(
    argv: list[str], log: Path | None = None, env: dict[str, str] | None = None
) -> subprocess.Popen:
    """A child in its own process group (a terminal's Ctrl-C reaches only us, and its
    group can be ended without touching anyone else's), output to `log` or nowhere;
    `env` None: this process's environment."""
    return procs.start(argv, log=log, env=env, cwd=ROOT)


def end(p: subprocess.Popen, grace: float = 30.0) -> None:
    """SIGTERM by PID (services flush and exit), wait, then SIGKILL its process group."""
    procs.end(p, grace, group=True)


class Procs:
    """Named children started here with a log each in `log_dir`, and ended here."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, argv: list[str], env: dict[str, str]) -> subprocess.Popen:
        """`env` on top of this process's environment, unbuffered output."""
        full = {**os.environ, "PYTHONUNBUFFERED": "1", **env}
        self.procs[name] = start(argv, self.log_dir / f"{name}.log", full)
        return self.procs[name]

    def stop(self, name: str, grace: float = 15.0) -> None:
        p = self.procs.pop(name, None)
        if p is not None:
            end(p, grace)

    def stop_all(self) -> None:
        """A router last, so services can still flush over a live bus."""
        for name in [n for n in self.procs if n != "router"] + ["router"]:
            self.stop(name)


def cpu_seconds(pid: int) -> float | None:
    """utime + stime of a process from /proc; None once it is gone. Not 0: a process
    that ended between two readings did not use no CPU, and a 0 would turn a difference
    into a negative share. Callers skip or refuse a None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children(pid: int) -> list[int]:
    """The direct children of a process (from every one of its threads)."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def role_of(pid: int) -> str:
    """A `macb serve` process's service id (or role), from its command line; else `?`."""
    argv = cmdline(pid) or []
    if "serve" not in argv:
        return "?"
    if "--id" in argv:
        return argv[argv.index("--id") + 1]
    i = argv.index("serve")
    return argv[i + 1] if i + 1 < len(argv) else "?"


def ours(pid: int, marks: tuple[str, ...]) -> bool:
    """Whether pid is still one of this run's processes (its command line names them)."""
    return procs.names_one_of(pid, marks)


class CpuSampler:
    """CPU seconds of a process's children, every `every` s in a thread, with their
    service ids: which service used the cores, and over which part of a run."""

    def __init__(self, parent: int, every: float = 0.25) -> None:
        self.parent, self.every = parent, every
        self.cpu: dict[int, float] = {}  # pid -> latest CPU seconds seen (kept once gone)
        self.series: list[tuple[float, dict[int, float]]] = []  # (monotonic, pid -> CPU s)
        self.roles: dict[int, str] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            now = {}
            for c in children(self.parent):
                s = cpu_seconds(c)
                if s is not None:
                    now[c] = self.cpu[c] = max(self.cpu.get(c, 0.0), s)
                    if self.roles.get(c, "?") == "?":
                        self.roles[c] = role_of(c)
            self.series.append((time.monotonic(), now))
            self._stop.wait(self.every)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def by_role(self) -> dict[str, float]:
        """CPU seconds per service over the whole run."""
        out: dict[str, float] = {}
        for c, s in self.cpu.items():
            out[self.roles.get(c, "?")] = out.get(self.roles.get(c, "?"), 0.0) + s
        return out

    def share(self, a: float, b: float) -> dict[str, float]:
        """Cores each service used between the samples nearest monotonic times a and b."""
        s0 = min(self.series, key=lambda x: abs(x[0] - a))
        s1 = min(self.series, key=lambda x: abs(x[0] - b))
        out: dict[str, float] = {}
        for c in s1[1]:
            if c in s0[1]:
                role = self.roles.get(c, "?")
                out[role] = out.get(role, 0.0) + (s1[1][c] - s0[1][c]) / (s1[0] - s0[0])
        return out


def kill_ours(pids: list[int], marks: tuple[str, ...]) -> None:
    """SIGKILL those of `pids` that still run one of ours (their command line names one
    of `marks`): what a parent that should have ended them left behind, and nothing
    else, even if a PID has been reused since."""
    for pid in pids:
        if ours(pid, marks):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
