"""Group processes (cli/group_procs.py): what they report, and what a stop leaves behind.

Real spawned processes, as `macb reproduce --local` runs them."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cli.group_procs import run_in_processes
from tests.harness import wait_for

ROOT = Path(__file__).resolve().parent.parent


def _bar_semaphores() -> str | None:
    """A progress bar in a group process, and the semaphores making it registered."""
    from multiprocessing import resource_tracker

    from tqdm import tqdm

    made: list[str] = []
    register = resource_tracker.register

    def counting(name: str, rtype: str) -> None:
        made.append(rtype)
        register(name, rtype)

    resource_tracker.register = counting
    try:
        with tqdm(total=1, file=io.StringIO()) as bar:
            bar.update(1)
    finally:
        resource_tracker.register = register
    return f"the bar made {made}" if made else None


def _bar_until_stopped(ready: str) -> str | None:
    """A group process that draws a bar, says so in `ready`, and waits to be ended."""
    from tqdm import tqdm

    with tqdm(total=10, file=io.StringIO()) as bar:
        bar.update(1)
        Path(ready).write_text("up")
        time.sleep(120)
    return None


def _fails(label: str) -> str | None:
    return f"{label} failed" if label == "b" else None


def test_each_process_reports_what_its_target_returned():
    tasks = [(label, (label,)) for label in "abc"]
    assert run_in_processes(_fails, tasks, jobs=2) == ["b failed"]


def test_a_group_processs_progress_bar_holds_no_semaphore():
    assert run_in_processes(_bar_semaphores, [("bar", ())], jobs=1) == []


@pytest.mark.timeout(120)
def test_a_sigtermed_command_leaves_no_semaphore_for_the_tracker_to_warn_of(tmp_path):
    ready = tmp_path / "ready"
    code = (
        "from cli.group_procs import run_in_processes\n"
        "from tests.test_group_procs import _bar_until_stopped\n"
        f"run_in_processes(_bar_until_stopped, [('g', ({str(ready)!r},))], jobs=1)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        wait_for(ready.exists, timeout=90, what="the group process's bar")
        os.kill(proc.pid, signal.SIGTERM)
        # Read to EOF: the resource tracker holds the same stderr and warns as it exits.
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "stopped by SIGTERM: ended 1 group process(es)" in err, err
    assert "leaked semaphore" not in err, err
