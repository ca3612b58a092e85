"""The processes `--local` trains its run groups in (cli/local.py's `run_groups`): started
`jobs` at a time, waited for, and never outliving the command that started them.

A campaign's group processes train for hours, and the command that started them is
ended in every way: SIGTERM from a restart, Ctrl-C (SIGINT), a closed terminal (SIGHUP),
SIGKILL. An orphaned group goes on writing its runs' folders, and the next `macb
reproduce` resumes the same runs beside it. So:

- while groups train, SIGTERM, SIGINT and SIGHUP to the command end every group process
  (SIGTERM, SIGKILL after a grace) and the command exits 128 + the signal with one line
  saying so (`Stopped`);
- each group process dies with the command however it ends, SIGKILL included
  (`shared.procs.die_with_parent`), and ignores SIGINT, which a terminal sends to the
  whole process group: the command ends it instead, once.

A group process ends where it is rather than at its next cut: cuts come at evaluation
points, minutes apart in a long figure, and are written so that an end at any moment
resumes from the newest one to the rows of not stopping (docs/reliability.md); what it
trained since its last cut is trained again.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
GRACE_S = 5.0  # from SIGTERM to SIGKILL for a group process


class Stopped(SystemExit):
    """The command was told to stop (a signal): its group processes are ended, and it
    exits 128 + the signal's number."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(128 + signum)


class StopSignals:
    """While in its `with` block (main thread only), SIGTERM, SIGINT and SIGHUP raise
    `Stopped`; inside `holding()` (a process being started, not yet in the caller's
    hands) a signal is only noted, and raised when the block ends."""

    def __init__(self) -> None:
        self.caught: list[int] = []
        self.held = False
        self.before: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        import threading

        if threading.current_thread() is threading.main_thread():  # else: Python's own
            self.before = {s: signal.signal(s, self.on_signal) for s in STOP_SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for s, handler in self.before.items():
            signal.signal(s, handler)

    def on_signal(self, signum: int, frame: Any) -> None:
        self.caught.append(signum)
        if not self.held:
            raise Stopped(signum)

    @contextmanager
    def holding(self) -> Iterator[None]:
        self.held = True
        try:
            yield
        finally:
            self.held = False
        if self.caught:
            raise Stopped(self.caught[0])


def say_stopped(stop: Stopped, ended: Sequence[int]) -> None:
    """The one line a stopped command prints."""
    name = signal.Signals(stop.signum).name
    procs = f"ended {len(ended)} group process(es) (PID {', '.join(map(str, ended))})"
    print(
        f"stopped by {name}: {procs if ended else 'training ended'}; the same command "
        "resumes the runs from their cuts",
        file=sys.stderr,
    )


def run_in_processes(
    target: Callable[..., str | None],
    tasks: Sequence[tuple[str, tuple]],
    jobs: int,
    start: Callable[[int], None] | None = None,
) -> list[str]:
    """`target(*args)` for each (label, args) in `tasks`, each in a spawned process of its
    own, `jobs` at a time; the messages of those that failed (what `target` returned,
    or how its process ended, labelled). `start(slot)` runs first in each process, with
    the slot (0 .. jobs-1) it holds while it lives (a GPU per slot). A stop signal ends
    them all and raises `Stopped`, the line printed."""
    import multiprocessing
    from multiprocessing.connection import wait

    ctx = multiprocessing.get_context("spawn")
    pending = list(tasks)
    live: dict[Any, tuple[Any, Any, str, int]] = {}  # sentinel -> (process, pipe, label, slot)
    free = list(range(jobs))
    failed: list[str] = []
    with StopSignals() as stops:
        try:
            while pending or live:
                while pending and len(live) < jobs:
                    label, args = pending.pop(0)
                    slot = free.pop(0)
                    recv, send = ctx.Pipe(duplex=False)
                    child_args = (os.getpid(), send, target, args, start, slot)
                    proc = ctx.Process(target=_child, args=child_args)
                    with stops.holding():  # a signal now would lose the process half started
                        try:
                            proc.start()
                        finally:
                            send.close()
                        live[proc.sentinel] = (proc, recv, label, slot)
                for sentinel in wait(list(live)):
                    proc, recv, label, slot = live.pop(sentinel)
                    free.append(slot)
                    message = _message(recv)
                    proc.join()
                    if message is None and proc.exitcode != 0:
                        message = f"{label}: its process ended ({_how(proc.exitcode)})"
                    if message:
                        failed.append(message)
        except Stopped as stop:
            procs = [p for p, _, _, _ in live.values()]
            end_processes(procs)
            say_stopped(stop, [p.pid for p in procs])
            raise
    return failed


def end_processes(procs: Sequence[Any], grace: float = GRACE_S) -> None:
    """SIGTERM (and SIGCONT, for one paused) each, SIGKILL what is left after `grace`,
    and reap them all: none outlives this call."""
    from shared.procs import send

    for p in procs:
        for sig in (signal.SIGTERM, signal.SIGCONT):
            if p.is_alive():
                send(p.pid, sig)
    deadline = time.monotonic() + grace
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            send(p.pid, signal.SIGKILL)
            p.join()


def _message(recv: Any) -> str | None:
    try:
        return recv.recv() if recv.poll() else None
    except (EOFError, OSError):  # ended without a word: a signal
        return None
    finally:
        recv.close()


def _how(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        return f"killed by {signal.Signals(-exitcode).name}"
    return f"exit code {exitcode}"


def _child(
    parent: int,
    send: Any,
    target: Callable[..., str | None],
    task: tuple,
    start: Callable[[int], None] | None = None,
    slot: int = 0,
) -> None:
    """A group process: dies with `parent`, leaves SIGINT to it, sends back what
    `target` returns. Its progress bars lock within the process: tqdm's default lock
    holds a semaphore, which a SIGTERMed process leaves for the resource tracker to
    warn of ("leaked semaphore"), and no other process shares a spawned child's lock."""
    import threading

    from tqdm import tqdm

    from shared.procs import die_with_parent

    die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    tqdm.set_lock(threading.RLock())
    if start is not None:
        start(slot)
    message = target(*task)
    send.send(message)
    send.close()
