"""A multi-hour `--local` campaign, restarted by hand: its group processes end with the
command whatever ends it (SIGTERM, SIGINT, SIGHUP, SIGKILL), one process at most
trains a run folder, groups on resume are as many as --jobs, and a torn or corrupt
metrics.jsonl is tolerated or refused by name, never a traceback. Real processes in
the test's own folders, ended by PID."""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import pytest

from cli.local import MetricsError, run_rows, split_groups
from shared import procs
from shared.persist import runlock
from tests.harness import macb, parents, spawn, wait_for

ARMS = (
    "task: speaker_listener\nalgo: cen-maddpg\nexplore: cen-macb\nk: 16\nepisodes: {episodes}\n"
    "eval_every: 5\neval_episodes: 2\nhidden: [32, 32]\nbatch_size: 16\nlearning_starts: 40\n"
    "learner_lanes: 1\n"
    "arms:\n  - {{name: counted, explore: cen-macb}}\n  - {{name: constant, explore: constant}}\n"
)
NAMES = ("constant-s0", "constant-s1", "counted-s0", "counted-s1")


# ---------------------------------------------------------------- grouping
def _sets(*sizes: int, state: str = "new") -> list[tuple[str, list[int]]]:
    out, start = [], 0
    for i, n in enumerate(sizes):
        out.append((f"{state}-{i}", list(range(start, start + n))))
        start += n
    return out


def _sizes(groups: list[tuple[str, list[int]]]) -> list[int]:
    return [len(m) for _, m in groups]


def test_groups_are_as_many_as_jobs_where_the_runs_allow():
    # two cut-sets of 6 (a resume at two cuts), 2 jobs: one group each, not 4 of 3
    two_cuts = split_groups(_sets(6, 6), jobs=2)
    assert _sizes(two_cuts) == [6, 6] and [s for s, _ in two_cuts] == ["new-0", "new-1"]
    assert split_groups(_sets(12), jobs=2) == [("new-0", list(range(6))),
                                               ("new-0", list(range(6, 12)))]  # fmt: skip
    assert _sizes(split_groups(_sets(11), jobs=2)) == [6, 5]  # as before: ceil first
    assert _sizes(split_groups(_sets(6, 6), jobs=4)) == [3, 3, 3, 3]
    assert _sizes(split_groups(_sets(6, 2), jobs=3)) == [3, 3, 2], "the widest is split"
    assert _sizes(split_groups(_sets(4, 4, 4), jobs=2)) == [4, 4, 4], "never merged"
    assert _sizes(split_groups(_sets(2), jobs=8)) == [1, 1], "a run is the smallest group"
    assert _sizes(split_groups(_sets(6, 6), jobs=2, max_runs=4)) == [4, 2, 4, 2]
    every = split_groups(_sets(5, 7), jobs=5)
    assert sorted(i for _, m in every for i in m) == list(range(12)) and len(every) == 5


# ---------------------------------------------------------------- torn rows
def test_a_torn_last_line_is_left_out_and_garbage_before_it_is_refused_by_line(tmp_path):
    path = tmp_path / "metrics.jsonl"
    path.write_text('{"episode": 10}\n{"episode": 20}\n{"episode": 3\x00\x00\n')
    assert [r["episode"] for r in run_rows(tmp_path)] == [10, 20], "killed mid-row"
    path.write_bytes(b'{"episode": 10}\n\x00\x00\x00\x00{"episode": 20}\n{"episode": 30}\n')
    with pytest.raises(MetricsError, match=rf"{path}, line 2: not a metric row"):
        run_rows(tmp_path)
    path.write_text('{"episode": 10}\n[1, 2]\n{"episode": 30}\n')
    with pytest.raises(MetricsError, match="line 2: not a metric row"):
        run_rows(tmp_path)


def test_a_run_folder_written_by_two_processes_is_refused_naming_the_line(tmp_path):
    """What two writers left (NUL holes mid-file): `macb run --local` and its page say
    which file and line and exit 2, without a traceback and without training."""
    config = tmp_path / "exp.yaml"
    config.write_text(ARMS.format(episodes=15))  # 3 rows: the 2nd torn
    args = ["run", str(config), "--local", "--seeds", "0", "--jobs", "1", "--quiet"]
    out = tmp_path / "out"
    assert macb(*args, "--out", str(out)).returncode == 0
    metrics = out / "counted-s0" / "metrics.jsonl"
    lines = metrics.read_bytes().splitlines(keepends=True)
    metrics.write_bytes(lines[0] + b"\x00" * 40 + b"".join(lines[1:]))
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    got = macb(*args, "--out", str(out))
    assert got.returncode == 2, got.stderr
    assert f"{metrics}, line 2: not a metric row" in got.stderr
    assert "Traceback" not in got.stderr
    after = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    assert after == before


# ---------------------------------------------------------------- one writer
def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def _stop(pid: int) -> None:
    """SIGSTOP `pid` and wait until every thread of it is stopped: a thread in a write or
    an fsync (a cut going to disk) stops only once that call is done, which on a loaded
    disk can take longer than any fixed sleep."""
    os.kill(pid, signal.SIGSTOP)

    def stopped() -> bool:
        states = []
        for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
            try:
                states.append(stat.read_text().rsplit(")", 1)[1].split()[0])
            except OSError:
                continue  # a thread that ended meanwhile
        return bool(states) and all(s in ("T", "t") for s in states)

    wait_for(stopped, timeout=30, what=f"PID {pid} stopped")


def test_a_second_process_on_a_run_folder_is_refused_naming_the_holder(tmp_path):
    out = tmp_path / "run"
    base = ["train", "--task", "speaker_listener", "--algo", "cen-maddpg", "--explore",
            "cen-macb", "--hidden", "16,16", "--batch-size", "8", "--learning-starts", "20",
            "--eval-every", "5", "--eval-episodes", "1", "--learner-lanes", "1",
            "--quiet"]  # fmt: skip
    first = spawn(*base, "--episodes", "5000", "--out", str(out), log=tmp_path / "first.log")
    try:
        wait_for(lambda: (out / "metrics.jsonl").exists() and (out / "cuts").exists()
                 and (out / ".lock").read_text().strip() == str(first.pid),
                 timeout=120, what="the first run's rows")  # fmt: skip
        _stop(first.pid)  # so that nothing changes but what the second does
        before = _snapshot(out)
        for second in (
            macb(*base, "--episodes", "5000", "--out", str(out)),
            macb("train", "--resume", str(out), "--quiet"),
        ):
            assert second.returncode == 2, second.stderr
            assert f"{out}: PID {first.pid} is training this run" in second.stderr
            assert "Traceback" not in second.stderr
            assert _snapshot(out) == before, "the refused process touched the folder"
        os.kill(first.pid, signal.SIGCONT)
    finally:
        procs.send(first.pid, signal.SIGCONT)
        procs.end(first, grace=5)
    assert runlock.is_locked(out) is None, "the kernel drops the lock with its holder"


# ---------------------------------------------------------------- signals
def _children(pid: int) -> set[int]:
    """Every live descendant of `pid`, from /proc."""
    parent_of = parents()
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for child, parent in parent_of.items():
            if parent == p and child not in found:
                found.add(child)
                todo.append(child)
    return found


def _groups_running(out: Path, parent: int) -> set[int]:
    """Once every run has its first cut: the group processes (the PIDs in the locks)."""
    if len(list(out.glob("*/cuts/cut-*.pt"))) < len(NAMES):
        return set()
    holders = {(out / n / ".lock").read_text().strip() for n in NAMES}
    pids = {int(h) for h in holders if h.isdigit()}
    return pids if len(pids) == 2 and pids <= _children(parent) else set()


@pytest.mark.slow  # each signal's case runs a campaign and resumes it: ~50 s alone
@pytest.mark.parametrize(
    "sig",
    [signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGKILL],
    ids=lambda s: signal.Signals(s).name,
)
def test_a_signalled_campaign_leaves_no_group_process_and_the_same_command_resumes(tmp_path, sig):
    config = tmp_path / "exp.yaml"
    config.write_text(ARMS.format(episodes=200))
    out = tmp_path / "out"
    args = ["run", str(config), "--local", "--seeds", "0", "1", "--jobs", "2", "--quiet",
            "--out", str(out)]  # fmt: skip
    log = tmp_path / "first.log"
    parent = spawn(*args, log=log)
    children: set[int] = set()
    try:
        groups = wait_for(lambda: _groups_running(out, parent.pid), timeout=180,
                          what="two group processes past their first cut")  # fmt: skip
        children = _children(parent.pid)
        assert groups <= children
        if sig == signal.SIGTERM:  # meanwhile a second command on the same runs: refused
            for pid in groups:
                _stop(pid)
            before = _snapshot(out)
            second = macb(*args)
            for pid in groups:
                os.kill(pid, signal.SIGCONT)
            assert second.returncode == 2, second.stderr
            assert "is training this run" in second.stderr and "Traceback" not in second.stderr
            assert any(f"PID {pid} is training" in second.stderr for pid in groups)
            assert _snapshot(out) == before
        os.kill(parent.pid, sig)
        code = parent.wait(timeout=30)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(procs.alive(p) for p in children):
            time.sleep(0.1)
        assert not [p for p in children if procs.alive(p)], "a group process outlived it"
    finally:
        for pid in _children(parent.pid) | children:  # ours, if the test failed midway
            if procs.alive(pid):
                procs.send(pid, signal.SIGKILL)
        procs.end(parent, grace=1)
    text = log.read_text()
    if sig == signal.SIGKILL:
        assert code == -signal.SIGKILL
    else:
        assert code == 128 + sig, text[-2000:]
        name = signal.Signals(sig).name
        (line,) = [x for x in text.splitlines() if x.startswith(f"stopped by {name}")]
        assert "ended 2 group process(es) (PID " in line and "resumes the runs" in line
        assert "Traceback" not in text
    if sig in (signal.SIGTERM, signal.SIGKILL):  # the same command goes on to the end
        again = macb(*args, timeout=600)
        assert again.returncode == 0, again.stderr[-3000:]
        assert "resuming from cut-" in again.stderr
        for name in NAMES:
            rows = [json.loads(x) for x in (out / name / "metrics.jsonl").read_text().splitlines()]
            assert rows[-1]["episode"] == 200 and (out / name / "checkpoint.pt").exists()
            starts = json.loads((out / name / "provenance.json").read_text())["starts"]
            assert len(starts) == 2 and isinstance(starts[1]["resumed_at"], int)
            assert 0 < starts[1]["resumed_at"] < 200


def test_a_group_process_dies_with_its_parent_even_when_armed_late(tmp_path):
    """die_with_parent: a child whose parent is gone before it armed the signal ends
    too (the check after arming)."""
    script = tmp_path / "orphan.py"
    script.write_text(
        "import os, sys, time\n"
        f"sys.path.insert(0, {str(Path(__file__).resolve().parents[1])!r})\n"
        "from shared.procs import die_with_parent\n"
        "time.sleep(1.0)  # the parent is gone by now\n"
        "print(die_with_parent(int(sys.argv[1])), flush=True)\n"
        "time.sleep(60)\n"
    )
    gone = procs.start([sys.executable, "-c", "import os; print(os.getpid())"], pipe=True)
    dead_parent = int(gone.communicate()[0])
    child = procs.start([sys.executable, str(script), str(dead_parent)], pipe=True)
    try:
        child.wait(timeout=30)
        assert child.returncode == -signal.SIGKILL
    finally:
        procs.end(child, grace=1)
