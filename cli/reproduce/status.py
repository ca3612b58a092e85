"""Where a figure's campaign stands: each run's episode of its target, its speed over the
last hour and the projected finish of the figure (`macb reproduce FIGURE --status`, and
the page's header).

Read from the runs' rows only (a `--local` campaign's folders, or a page's points), so it
works while the campaign trains and after it stopped, and never touches a run. The speed
is measured on each run's own clock, its rows' `wall_s` (summed over its starts, so a
stop between two starts is not counted as slowness); the file's modification time only
says how long ago the last row was written, i.e. whether the campaign is running now.
The runs of a group step together, so the figure finishes with its slowest run: that
run's remaining episodes at its speed.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Collection
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

HOUR_S = 3600.0
STALE_S = 600.0  # no row for this long: the campaign is not running


@dataclass(frozen=True)
class RunProgress:
    run: str
    arm: str
    seed: int
    target: int  # the episodes it is to run
    episode: int = 0  # its last stored row's (0: no row)
    speed: float | None = None  # episodes per hour of its own clock, over its last hour
    span_h: float = 0.0  # the clock hours that speed is measured over (at most ~1)
    written: float | None = None  # when its last row was written (epoch s; folders only)
    note: str = ""  # why it has no rows to read, if so
    stopped: bool = False  # ended by its `early_stop` rule at `episode`: finished

    @property
    def started(self) -> bool:
        """It has a row (a run ended by its rule at episode 0 has none, and is done)."""
        return self.episode > 0

    @property
    def left(self) -> int:
        return 0 if self.stopped else max(0, self.target - self.episode)

    @property
    def hours_left(self) -> float | None:
        if not self.left:
            return 0.0
        return self.left / self.speed if self.speed else None


def measure(
    run: str, arm: str, seed: int, target: int, episodes: np.ndarray, wall: np.ndarray
) -> RunProgress:
    """A run's progress from its rows (episode and `wall_s`, in episode order): the speed
    between its last row and the last row an hour of its clock before (its first row
    when it has run less than an hour)."""
    episodes, wall = np.asarray(episodes), np.asarray(wall, dtype=float)
    if not len(episodes):
        return RunProgress(run, arm, seed, target)
    ok = ~np.isnan(wall)
    if not ok.any():  # rows without a clock: how far, not how fast
        return RunProgress(run, arm, seed, target, int(episodes[-1]))
    episodes, wall = episodes[ok], wall[ok]
    last, now = int(episodes[-1]), float(wall[-1])
    before = np.flatnonzero(wall <= now - HOUR_S)
    i = int(before[-1]) if len(before) else 0
    span = now - float(wall[i])
    speed = (last - int(episodes[i])) / span * HOUR_S if span > 0 else None
    return RunProgress(run, arm, seed, target, last, speed, span / HOUR_S)


@dataclass(frozen=True)
class FigureProgress:
    runs: list[RunProgress]
    target: int  # the figure's run length (every run's, unless --episodes cut it)

    @property
    def done(self) -> bool:
        return all(r.left == 0 for r in self.runs)

    def slowest(self) -> RunProgress | None:
        """The started run that finishes last at its speed (None: some started,
        unfinished run has no speed to project from, or no started run is left)."""
        left = [r for r in self.runs if r.left and r.started]
        if not left or any(r.hours_left is None for r in left):
            return None
        return max(left, key=lambda r: r.hours_left or 0.0)

    def by_arm(self) -> dict[str, int]:
        """Each arm's episode: the least its seeds reached."""
        out: dict[str, int] = {}
        for r in self.runs:
            out[r.arm] = min(out.get(r.arm, r.episode), r.episode)
        return out

    def not_started(self) -> list[str]:
        """The arms none of whose runs has a row yet, in the figure's order: a campaign
        that runs its arms in turns (figure 8's sparse arms, then its dense ones)."""
        started = {r.arm for r in self.runs if r.started or not r.left}
        return [a for a in self.by_arm() if a not in started]

    def reached(self) -> str:
        """'N of T episodes' over the arms started (the arms not started named after
        it), with each arm's when they differ, and the runs their `early_stop` rule
        ended (finished short of T)."""
        arms = self.by_arm()
        waiting = self.not_started()
        if len(waiting) == len(arms):  # nothing started: the figure is at 0, no more
            waiting = []
        begun = {a: e for a, e in arms.items() if a not in waiting}
        low = min(begun.values(), default=0)
        text = f"{low:,} of {self.target:,} episodes"
        if waiting:
            text += f" in the {len(begun)} arm(s) started"
        if len(set(begun.values())) > 1:
            text += " (per arm: " + "; ".join(f"{a} {e:,}" for a, e in begun.items()) + ")"
        if waiting:
            runs = sum(1 for r in self.runs if r.arm in waiting)
            text += f"; not started: {', '.join(waiting)} ({runs} run(s))"
        stopped = [r for r in self.runs if r.stopped]
        if stopped:
            text += f"; {len(stopped)} run(s) ended by their early_stop rule (finished): " + (
                ", ".join(f"{r.run} at {r.episode:,}" for r in stopped)
            )
        return text

    def speeds(self) -> str:
        known = [r.speed for r in self.runs if r.speed is not None and r.left]
        if not known:
            return "no speed yet"
        lo, hi = min(known), max(known)
        span = f"{lo:,.0f}" if round(lo) == round(hi) else f"{lo:,.0f}-{hi:,.0f}"
        return f"{span} episodes per hour"

    def finish(self, now: float, counted: str = "") -> str:
        """The projected finish counted from `now` (epoch s), and whose it is; `counted`
        says from when, after the projection."""
        if self.done:
            return "complete: every run reached its target"
        slow = self.slowest()
        queued = sum(1 for r in self.runs if r.left and not r.started)
        after = f"; then {queued} run(s) not started, not projected" if queued else ""
        if slow is None:
            waiting = sum(1 for r in self.runs if r.left and r.started and r.hours_left is None)
            if not waiting and any(r.started for r in self.runs):  # between two turns
                return f"the runs started are finished; {queued} run(s) not started, not projected"
            if not waiting:
                return f"no projection: no run has started ({queued} to run)"
            return (
                f"no projection: {waiting} unfinished run(s) have no speed (rows with "
                f"`wall_s`){after}"
            )
        h = slow.hours_left or 0.0
        when = datetime.fromtimestamp(now + h * HOUR_S, UTC)
        return (
            f"projected finish {when:%Y-%m-%d %H:%M} UTC"
            + (" of the runs started" if queued else "")
            + f", in {h:,.1f} h of running (the slowest group's: {slow.run}, {slow.left:,} "
            f"episodes left at {slow.speed:,.0f}/h){counted}{after}"
        )


def from_points(
    exp: dict[str, Any], points: dict[str, dict[str, np.ndarray]], target: int
) -> FigureProgress:
    """A page's runs (its experiment and their columns, cli/reproduce/analysis.py)."""
    runs = []
    for r in exp.get("runs") or []:
        cols = points.get(r["id"]) or {}
        episodes = cols.get("episode", np.zeros(0))
        wall = cols.get("wall_s", np.full(len(episodes), math.nan))
        run_target = int((r.get("config") or {}).get("episodes") or target)
        p = measure(r["id"], r["arm"], r["seed"], run_target, episodes, wall)
        runs.append(replace(p, stopped=bool(len(cols.get("stop", ())))))
    return FigureProgress(runs, _target(runs, target))


def _target(runs: list[RunProgress], default: int) -> int:
    return max((r.target for r in runs), default=default)


def page_line(progress: FigureProgress, now: float) -> str:
    """The page header's line: how far it got, how fast, when it ends."""
    built = datetime.fromtimestamp(now, UTC)
    if progress.done:
        return (
            f"- Progress (page built {built:%Y-%m-%d %H:%M} UTC): complete, {progress.reached()}."
        )
    return (
        f"- Progress (page built {built:%Y-%m-%d %H:%M} UTC): {progress.reached()}; speed "
        f"over the last hour of each run's own clock (its rows' `wall_s`): "
        f"{progress.speeds()}; {progress.finish(now, ', counted from the build')}."
    )


# ---------------------------------------------------------------- --status on folders
def tail_rows(path: Path, seconds: float = HOUR_S) -> list[dict[str, Any]]:
    """The rows of a metrics.jsonl from the last one `seconds` of its `wall_s` back (and
    the one before them), reading blocks from the end: a 40,000-row file is neither read
    nor parsed whole. A torn last line (a row being written) is skipped."""
    if not path.exists():
        return []
    with path.open("rb") as f:
        size = f.seek(0, 2)
        block = 1 << 18
        while True:
            start = max(0, size - block)
            f.seek(start)
            lines = f.read(size - start).splitlines()
            if start:  # the first line may be cut: read from the next one
                lines = lines[1:]
            rows, reached = _rows_back(lines, seconds)
            if reached or not start:
                return rows
            block *= 4


def _rows_back(lines: list[bytes], seconds: float) -> tuple[list[dict[str, Any]], bool]:
    """(the rows from the end back to one `seconds` before the last, in order; whether
    one that old was found)."""
    rows: list[dict[str, Any]] = []
    for line in reversed(lines):
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if not isinstance(row, dict) or "episode" not in row:
            continue
        rows.append(row)
        wall, last = row.get("wall_s"), rows[0].get("wall_s")
        if (
            isinstance(wall, int | float)
            and isinstance(last, int | float)
            and wall <= last - seconds
        ):
            return rows[::-1], True
    return rows[::-1], False


def read_folders(runs: list[Any], runs_dir: Path, target: int) -> FigureProgress:
    """Each run (cli.local.LocalRun) from its folder under runs_dir."""
    from cli.local import config_conflict

    out = []
    for r in runs:
        folder = runs_dir / r.name
        path = folder / "metrics.jsonl"
        if why := config_conflict(folder, r.config):
            out.append(RunProgress(r.name, r.arm, r.seed, r.config.episodes, note=why))
            continue
        rows = tail_rows(path)
        episodes = np.array([int(x["episode"]) for x in rows], dtype=np.int64)
        wall = np.array([_num(x.get("wall_s")) for x in rows], dtype=float)
        p = measure(r.name, r.arm, r.seed, r.config.episodes, episodes, wall)
        written = path.stat().st_mtime if path.exists() else None
        note = "" if rows else "not started"
        stopped = bool(rows and rows[-1].get("stop_reason"))
        out.append(replace(p, written=written, note=note, stopped=stopped))
    return FigureProgress(out, _target(out, target))


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else math.nan


def _ago(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s ago"
    if seconds < 2 * HOUR_S:
        return f"{seconds / 60:.0f} min ago"
    return f"{seconds / HOUR_S:.1f} h ago"


def status_text(name: str, progress: FigureProgress, runs_dir: Path, now: float) -> str:
    """What `--status` prints: a line per run, then the figure's."""
    when = datetime.fromtimestamp(now, UTC)
    lines = [f"{name}: {len(progress.runs)} run(s) in {runs_dir} (read {when:%Y-%m-%d %H:%M} UTC)"]
    width = max((len(r.run) for r in progress.runs), default=3)
    lines.append(f"{'run':<{width}}  {'episode':>24}  {'episodes/h':>16}  last row")
    for r in progress.runs:
        share = f"{r.episode:,} of {r.target:,} ({r.episode / r.target:.1%})"
        speed = "-" if r.speed is None else f"{r.speed:,.0f}"
        if r.speed is not None and r.span_h < 0.99:
            speed += f" ({r.span_h:.2f} h)"
        last = r.note or (_ago(now - r.written) if r.written else "-")
        if r.stopped:
            last += "; ended by its early_stop rule (finished)"
        lines.append(f"{r.run:<{width}}  {share:>24}  {speed:>16}  {last}")
    lines.append(
        "speed: episodes per hour of each run's own clock (its rows' wall_s, summed over "
        "its starts), over the last hour of it (the hours in brackets when less has run)"
    )
    lines.append(f"figure: {progress.reached()}; {progress.finish(now)}")
    written = [r.written for r in progress.runs if r.written]
    if not progress.done and written and now - max(written) > STALE_S:
        lines.append(
            f"no run has written a row for {_ago(now - max(written))[:-4]}: the campaign is "
            "not running (the same `macb reproduce ... --local` command resumes it); the "
            "finish counts from a restart now"
        )
    return "\n".join(lines)


def print_status(
    name: str, runs: list[Any], runs_dir: Path, target: int, siblings: Collection[str] = ()
) -> int:
    """`macb reproduce FIGURE --status`: 0, or 2 when there is no runs folder, when
    none of the runs has a folder in it while it holds a `runs` folder (OUT given for
    OUT/runs), or when a run's folder holds another config's run (another --profile,
    --episodes: named), or when it holds other runs and none of these nor of `siblings`
    (the figure's other arms). Runs not started yet (queued on Slurm, arms that run
    later) are shown so."""
    if not runs_dir.is_dir():
        print(f"macb reproduce --status: no runs folder {runs_dir}", file=sys.stderr)
        return 2
    if not any((runs_dir / r.name).is_dir() for r in runs) and (runs_dir / "runs").is_dir():
        print(
            f"macb reproduce --status: none of the {len(runs)} run(s) selected has a folder in "
            f"{runs_dir}, which holds a runs folder: give --runs {runs_dir / 'runs'}",
            file=sys.stderr,
        )
        return 2
    from cli.local import TRAINED_WITH, config_conflicts, foreign_runs

    if why := foreign_runs(runs, runs_dir, siblings):
        print(f"macb reproduce --status: {why}", file=sys.stderr)
        return 2
    if conflicts := config_conflicts(runs, runs_dir):  # their rows are not these runs'
        for line in conflicts:
            print(f"macb reproduce --status: {line}", file=sys.stderr)
        print(f"macb reproduce --status: {TRAINED_WITH} or another --runs", file=sys.stderr)
        return 2
    progress = read_folders(runs, runs_dir, target)
    print(status_text(name, progress, runs_dir, time.time()))
    return 0
