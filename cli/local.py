"""Many runs in this process as run groups (cli/trainer.py), without the bus:
what `macb train --seeds`, `macb run --local` and `macb reproduce --local` share.

Each run writes to its own folder under OUT (metrics.csv/jsonl, config.json,
provenance.json, checkpoint.pt, cuts/), exactly what `macb train --out` writes for it
alone. Runs are grouped by what they can share (`form_groups`); the same command run
again continues where it stopped: complete runs are skipped, runs that stopped at one
cut resume together, runs never started start together. A folder holding another
config's run is refused, never overwritten.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import socket
import sys
import time
import uuid
from collections.abc import Collection
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from shared.config import TrainConfig


def add_group_flags(parser: argparse.ArgumentParser, cluster: str = "") -> None:
    """`--group-size` and `--jobs`: how `--local` runs split into groups and processes
    (`cluster`: what --group-size does without --local, if anything)."""
    parser.add_argument(
        "--group-size",
        type=int,
        metavar="N",
        help="--local: at most N runs per group (default: the runs that can share one, "
        "split into --jobs groups)" + cluster,
    )
    parser.add_argument(
        "--jobs",
        type=int,
        metavar="N",
        help="--local: groups at a time, each in a process of its own (default: one per "
        "CPU, each group's update on the runs' `threads`, 1 by default; one per GPU when "
        "the runs' device is one, `cuda` giving each process a GPU of its own)",
    )


def group_flag_error(args: argparse.Namespace, *flags: str) -> str | None:
    """The first of `--group-size`, `--jobs` (and `flags`, e.g. "--threads") below 1."""
    for flag in ("--group-size", "--jobs", *flags):
        value = getattr(args, flag.lstrip("-").replace("-", "_"))
        if value is not None and value < 1:
            return f"{flag} {value}: give N >= 1"
    return None


log = logging.getLogger("macb.local")


def default_jobs(configs: list[TrainConfig]) -> int:
    """Groups at a time when --jobs is not given: one per CPU on the CPU; on a GPU one
    per GPU the runs' device names (every GPU for a bare `cuda`, one for `cuda:N`): a
    group's update keeps its GPU busy, and several groups on one GPU only take turns."""
    from shared.core.learners.precision import device_count

    devices = {c.device for c in configs if c.device != "cpu"}
    if not devices:
        return os.cpu_count() or 1
    return sum(max(1, device_count(d)) for d in devices)


def device_error(configs: list[TrainConfig]) -> str | None:
    """Why a device the runs name cannot be used here, or None: said once, before any
    group starts, instead of by every group as it builds its learner."""
    devices = sorted({c.device for c in configs} - {"cpu"})
    if not devices:
        return None
    from shared.core.learners.precision import DeviceError, resolve_device

    for device in devices:
        try:
            resolve_device(device)
        except DeviceError as err:
            return str(err)
    return None


def _spread_devices(configs: list[TrainConfig], jobs: int) -> str | None:
    """The bare accelerator name (`cuda`, `xpu`) whose devices the `jobs` processes take
    in turn (one each when there are as many processes as devices), or None: every run
    on the CPU, on one device, or on a device named by its number."""
    from shared.core.learners.precision import device_count

    devices = {c.device for c in configs}
    if len(devices) != 1 or jobs < 2:
        return None
    device = devices.pop()
    return device if ":" not in device and device_count(device) > 1 else None


def _take_device(kind: str, slot: int) -> None:
    """A group process's start: it takes the device of `kind` its slot names as its own,
    so the runs' `device: cuda` means that GPU in it (their configs stay as given)."""
    import torch

    from shared.core.learners.precision import device_count

    getattr(torch, kind).set_device(slot % device_count(kind))


@dataclass
class LocalRun:
    """One run of a local experiment: its folder name (its id), arm and config."""

    name: str
    arm: str | None
    seed: int
    config: TrainConfig


def folder_name(text: str) -> str:
    """A run's name as a folder name (letters, digits, '.', '_', '-')."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "run"


class MetricsError(ValueError):
    """A run's metrics.jsonl with a line that is not a row before its last one: refused,
    naming the file and the line (a torn last line is a row being written, or the last
    one of a killed process: left out)."""


class Refused(SystemExit):
    """`run_groups` refused before anything ran (a run's folder holds another config's
    run, another process trains a run, a run's rows do not read), the reason printed:
    the command exits 2, writing nothing."""

    def __init__(self) -> None:
        super().__init__(2)


def run_rows(folder: Path) -> list[dict[str, Any]]:
    """A run's rows as written so far (`cli.runs_folder.jsonl_rows`: a row being written
    or a torn last line is left out). A line before the last that does not read is
    refused: `MetricsError`, naming the file and the line."""
    from cli.runs_folder import RowError, jsonl_rows

    path = folder / "metrics.jsonl"
    if not path.exists():
        return []
    try:
        return jsonl_rows(path)
    except RowError as err:
        raise MetricsError(
            f"{path}, {err}; only a torn last line is left out. Were two processes writing "
            "this run? Its rows cannot be read: move the folder away (the same command "
            "then trains it afresh)"
        ) from None
    except OSError as err:
        raise MetricsError(f"{path}: cannot be read ({err})") from None


def _same_config(folder: Path, cfg: TrainConfig) -> bool:
    return (folder / "config.json").exists() and config_conflict(folder, cfg) is None


def config_conflict(folder: Path, cfg: TrainConfig) -> str | None:
    """Why `folder` holds another config's run ('field: a in the folder, b in the run', or
    its config.json does not read), or None (no config written there yet, or the same)."""
    from shared.persist.checkpoint import folder_config_difference

    return folder_config_difference(folder, cfg.model_dump(mode="json"))


# What to do about folders of another config's runs (config_conflicts), said after them.
TRAINED_WITH = (
    "give the flags these runs were trained with (--profile, --episodes, --seeds, --precision, ...)"
)


def config_conflicts(runs: list[LocalRun], out: Path) -> list[str]:
    """One line per run whose folder under `out` holds another config's run ('FOLDER:
    holds a run of another config (why)'): its rows are not this run's, so nothing may
    train on, plot or report them as this run's."""
    return [
        f"{out / r.name}: holds a run of another config ({why})"
        for r in runs
        if (why := config_conflict(out / r.name, r.config))
    ]


def foreign_runs(
    runs: list[LocalRun], runs_dir: Path, siblings: Collection[str] = ()
) -> str | None:
    """Why `runs_dir` is not these runs' folder when none of them has a folder there but
    other runs do (other --seeds, another figure's folder: a mistake, where an empty
    folder is a campaign not started yet), or None. `siblings`: the names of runs of the
    same campaign that are not asked for (a figure's other arms: arms that run later are
    not started, not a mistake)."""
    if not runs_dir.is_dir() or any((runs_dir / r.name).is_dir() for r in runs):
        return None
    others = sorted(
        d.name
        for d in runs_dir.iterdir()
        if d.is_dir() and (d / "config.json").is_file() and d.name not in siblings
    )
    if not others:
        return None
    listed = ", ".join(others[:4]) + (f" and {len(others) - 4} more" if len(others) > 4 else "")
    return (
        f"none of the {len(runs)} run(s) selected has a folder in {runs_dir}, which holds "
        f"other runs ({listed}): give the flags they were trained with (--seeds, --arms, "
        "--profile, ...) or their folder"
    )


def run_state(folder: Path, cfg: TrainConfig) -> str:
    """'done' (every episode run, or ended by its `early_stop` rule, checkpoint
    written), 'cut-<episode>' (can resume from its newest cut, of that episode) or
    'new'."""
    if not _same_config(folder, cfg):
        return "new"
    rows = run_rows(folder)
    ended = rows and (rows[-1].get("episode") == cfg.episodes or rows[-1].get("stop_reason"))
    if ended and (folder / "checkpoint.pt").exists():
        return "done"
    cuts = sorted((folder / "cuts").glob("cut-*.pt"))
    if cuts:
        return f"cut-{int(cuts[-1].stem.split('-')[1])}"
    return "new"


def run_groups(
    runs: list[LocalRun],
    out: Path,
    max_runs: int | None = None,
    quiet: bool = False,
    cut_every_s: float = 60.0,
    jobs: int | None = 1,
) -> int:
    """Train `runs` as groups under `out`, `jobs` groups at a time in processes of their
    own (None: `default_jobs`), continuing what an earlier call left; 0 when every run
    completed, 2 when a group could not resume (the reason printed).

    Complete runs are skipped one by one; the others are grouped by what they share and
    by where they stopped (runs that stopped together, at one cut, resume together;
    runs never started start together), so adding arms to a figure later neither
    restarts nor holds back the runs already under way. Without `max_runs`, the groups
    are split further until there are `jobs` of them where the runs allow (`split_groups`),
    one per process: on a CPU the products of one thread per group keep the cores busier
    than two threads on one.

    A run whose folder holds another config's run, that another process trains, or
    whose rows cannot be read, and runs for a device not here, end the command before
    anything is trained or written:
    `Refused` (a SystemExit, 2), the reason printed; the caller writes no page or plot
    either. SIGTERM, SIGINT or SIGHUP while it trains
    ends every group process and raises `Stopped` (a SystemExit, 128 + the signal), one
    line printed; the group processes die with this one however it ends
    (cli/group_procs.py)."""
    from cli.group_procs import Stopped, StopSignals, run_in_processes, say_stopped
    from shared.persist import runlock

    # A folder holding another config's run is refused, not overwritten: its results
    # may be all someone has (another --episodes, --threads, an edited file, ...).
    # Refused, not a return code: the caller's page or summary would show its rows.
    if conflicts := config_conflicts(runs, out):
        for line in conflicts:
            print(f"{line}; move it away or give another --out: nothing was run", file=sys.stderr)
        raise Refused()
    from cli.runs_folder import unwritable

    if why := device_error([r.config for r in runs]):
        print(f"{why}: nothing was run", file=sys.stderr)
        raise Refused()  # (a return code would let the caller go on to a page)
    if why := unwritable(out, make=True):  # (after every refusal that writes nothing)
        print(f"{out}: cannot write there ({why}): nothing was run", file=sys.stderr)
        raise Refused()
    jobs = jobs or default_jobs([r.config for r in runs])
    # One writer per run folder: a run another process trains is refused before any
    # group starts (each group takes its folders' locks too, for a race with this look).
    held = [(r, pid) for r in runs if (pid := runlock.is_locked(out / r.name)) is not None]
    for r, pid in held:
        print(runlock.RunLocked(out / r.name, pid or None), file=sys.stderr)
    if held:
        raise Refused()
    try:
        groups = plan_groups(runs, out, max_runs, jobs)
    except MetricsError as err:
        print(err, file=sys.stderr)
        raise Refused() from None
    command = command_id()
    tasks = []
    for n, (state, members) in enumerate(groups, 1):
        chosen = [runs[i] for i in members]
        what = f"group {n}/{len(groups)} ({len(chosen)} runs: {chosen[0].config.task})"
        resume = state != "new"
        print(f"{what}: {'resuming from ' + state if resume else 'starting'}", file=sys.stderr)
        args = (
            [r.config.model_dump(mode="json") for r in chosen],
            [str(out / r.name) for r in chosen],
            not quiet,
            resume,
            cut_every_s,
            what,
            (n - 1) % max(jobs, 1) if jobs > 1 else None,
            command,
        )
        tasks.append((what, args))
    if jobs <= 1 or len(tasks) <= 1:
        try:
            with StopSignals():
                failed = [m for _, t in tasks if (m := _train_group_job(*t)) is not None]
        except Stopped as stop:
            say_stopped(stop, [])
            raise
    else:
        spread = _spread_devices([r.config for r in runs], jobs)
        start = None if spread is None else partial(_take_device, spread)
        failed = run_in_processes(_train_group_job, tasks, jobs, start)
    for message in failed:
        print(message, file=sys.stderr)
    return 2 if failed else 0


def command_id() -> str:
    """What names one `run_groups` call in its runs' provenance: every group it starts,
    however much later, is one restart of a campaign. A Slurm array job's tasks, one
    call each, share their job's id (and a requeue is a restart of its own)."""
    job = os.environ.get("SLURM_ARRAY_JOB_ID") or os.environ.get("SLURM_JOB_ID")
    if job:
        return f"slurm-{job}-{os.environ.get('SLURM_RESTART_COUNT') or 0}"
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return f"{socket.gethostname()}-{stamp}-{uuid.uuid4().hex[:8]}"


def plan_groups(
    runs: list[LocalRun], out: Path, max_runs: int | None = None, jobs: int | None = 1
) -> list[tuple[str, list[int]]]:
    """The groups `run_groups` trains (and `--launcher slurm` submits, one task each):
    (the state they start from, 'new' or 'cut-<episode>'; the indices in `runs` of
    their members). Complete runs are left out, and said so. `jobs` None: `default_jobs`.
    `MetricsError` for a run whose rows cannot be read."""
    jobs = jobs or default_jobs([r.config for r in runs])
    states = [run_state(out / r.name, r.config) for r in runs]
    todo = [i for i, s in enumerate(states) if s != "done"]
    if len(todo) < len(runs):
        print(f"{len(runs) - len(todo)} of {len(runs)} runs complete, skipped", file=sys.stderr)
    by_state: dict[str, list[int]] = {}
    for i in todo:
        by_state.setdefault(states[i], []).append(i)
    from shared.groups import form_groups

    shared = [
        (state, [idx[j] for j in g])
        for state, idx in by_state.items()
        for g in form_groups([runs[i].config for i in idx])
    ]
    return split_groups(shared, jobs, max_runs)


def split_groups(
    shared: list[tuple[str, list[int]]], jobs: int, max_runs: int | None = None
) -> list[tuple[str, list[int]]]:
    """Groups of runs that must train apart (another cut, another task or network) split
    into the groups trained: with `max_runs`, into pieces of at most that many; else
    only while there are fewer groups than `jobs`, the group with the most runs per
    piece split once more each time, into pieces that differ by one run at most.

    So the groups at a time are `jobs` where the runs allow it: 12 fresh runs and 2 jobs
    give 2 groups of 6, as do 12 runs resumed from two cuts (6 at each), which split
    per cut into `jobs` each would give 4 groups of 3, two of them waiting for the
    others' hours. Each group's rows are its runs' alone, so how runs are grouped never
    changes a result, only how long the figure takes."""
    if max_runs:
        return [
            (state, members[k : k + max_runs])
            for state, members in shared
            for k in range(0, len(members), max_runs)
        ]
    pieces = [1] * len(shared)
    while sum(pieces) < jobs:
        room = [i for i, (_, m) in enumerate(shared) if len(m) > pieces[i]]
        if not room:
            break
        widest = max(room, key=lambda i: (-(-len(shared[i][1]) // pieces[i]), -i))
        pieces[widest] += 1
    out = []
    for (state, members), n in zip(shared, pieces, strict=True):
        size, extra = divmod(len(members), n)
        start = 0
        for k in range(n):
            end = start + size + (k < extra)
            out.append((state, members[start:end]))
            start = end
    return out


def _train_group_job(
    configs: list[dict[str, Any]],
    folders: list[str],
    progress: bool,
    resume: bool,
    cut_every_s: float,
    what: str,
    position: int | None = None,
    command: str | None = None,
) -> str | None:
    """One group, in this process or a pool's: None, or why it could not resume."""
    from cli.trainer import train_group
    from shared.config import make_config
    from shared.core.learners.precision import DeviceError
    from shared.persist.cuts import CutError
    from shared.persist.runlock import RunLocked
    from shared.run.rollout import WorldError

    try:
        train_group(
            [make_config(c) for c in configs],
            [Path(f) for f in folders],
            progress=progress,
            resume=resume,
            cut_every_s=cut_every_s,
            desc=what,
            position=position,
            command=command,
        )
    except CutError as err:
        return f"{what}: cannot resume: {err}"
    except RunLocked as err:
        return f"{what}: {err}"
    except (DeviceError, WorldError) as err:
        return f"{what}: {err}"
    except Exception as err:  # any other failure of one group: said, the others go on
        import traceback

        return f"{what}: failed: {type(err).__name__}: {err}\n{traceback.format_exc()}"
    return None


def local_experiment(name: str, seeds: list[int], runs: list[LocalRun], out: Path) -> dict:
    """The runs under `out` as the API would describe their experiment (what the
    report reads): each run's status, config, latest provenance, resumes (the page's
    restarts) and the CPU and code of each start (`start_cpus`, `start_codes`).
    `MetricsError` for a run whose rows cannot be read."""
    from shared.persist import provenance

    described: list[dict[str, Any]] = []
    for r in runs:
        folder = out / r.name
        state = run_state(folder, r.config)
        starts = []
        try:
            starts = provenance.read(folder / provenance.FILE)
        except provenance.ProvenanceError as err:
            log.warning("%s", err)
        rows = run_rows(folder) if state == "done" else []
        why = rows[-1].get("stop_reason") if rows else None
        described.append(
            {
                "id": r.name,
                "arm": r.arm or r.name,
                "seed": r.seed,
                "config": r.config.model_dump(mode="json"),
                "status": "completed" if state == "done" else "incomplete",
                # ended by its early_stop rule: why, and at which episode
                "reason": why,
                "stopped_at": int(rows[-1]["episode"]) if why else None,
                "live": {"provenance": starts[-1] if starts else None},
                "resumes": [_resume(s) for s in starts[1:]] if starts else None,
                "start_cpus": [start_cpu(s) for s in starts] if starts else None,
                "start_codes": [s.get("code") for s in starts] if starts else None,
            }
        )
    counts: dict[str, int] = {}
    for d in described:
        counts[d["status"]] = counts.get(d["status"], 0) + 1
    done = all(d["status"] == "completed" for d in described)
    walls = [rows[-1].get("wall_s", 0.0) for r in runs if (rows := run_rows(out / r.name))]
    return {
        "wall_s": max(walls, default=0.0),
        "id": f"local:{out}",
        "name": name,
        "status": "completed" if done else "incomplete",
        "counts": counts,
        "seeds": seeds,
        "runs": described,
    }


def start_cpu(start: Any) -> str | None:
    """The CPU model a start ran on (None where its provenance does not say, or is no
    record): a run's rows round as the CPU of the start that computed them does."""
    machine = start.get("machine") if isinstance(start, dict) else None
    cpu = machine.get("cpu") if isinstance(machine, dict) else None
    return cpu if isinstance(cpu, str) else None


def _resume(start: dict[str, Any]) -> dict[str, Any]:
    """A start after a run's first, as the page's header names it: the episode it went on
    from (None before starts recorded it), its code, its CPU, when, and the command that
    made it (None before starts named it)."""
    episode = start.get("resumed_at")
    command = start.get("command")
    return {
        "episode": episode if isinstance(episode, int) else None,
        "code": start.get("code"),
        "cpu": start_cpu(start),
        "started": start.get("started"),
        "command": command if isinstance(command, str) else None,
    }


def local_points(runs: list[LocalRun], out: Path) -> dict[str, list[dict[str, Any]]]:
    """Each run's metric rows, read from its folder."""
    return {r.name: run_rows(out / r.name) for r in runs}


def expand_body(body: dict[str, Any]) -> tuple[str, list[int], list[LocalRun]]:
    """An experiment body (what POST /experiments takes) as the API expands it: its
    name, seeds and runs (arms outer, grid points, seeds inner), each named
    `<arm>-s<seed>` (the arm's name is its grid point's without arms)."""
    from services.api.schemas import ExperimentCreate

    exp = ExperimentCreate.model_validate(body)
    runs = []
    for e in exp.expand():
        arm = e["arm"]
        name = f"{folder_name(arm)}-s{e['seed']}"
        runs.append(LocalRun(name, arm, e["seed"], e["config"]))
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        raise ValueError("two runs would share a folder name; name the arms apart")
    return exp.name or exp.default_name(), exp.seed_list(), runs
