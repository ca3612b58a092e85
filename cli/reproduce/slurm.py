"""`macb reproduce FIGURE --local --launcher slurm`: the figure's run groups as the tasks
of one Slurm array job, followed to the end (or left with --detach), then the page.

Each group of the `--local` plan (cli.local.plan_groups) becomes one array task whose
command is that group's own `macb reproduce ... --local --group-runs RUN...`: it trains
those runs into their folders in the runs folder (a filesystem every node shares) and,
run again, resumes them from their newest cuts. So a task that Slurm requeues
(`--requeue`: preemption, `scontrol requeue`, a node lost) starts from its cut rather
than from the beginning, and a task that ended unfinished (cancelled, out of time,
failed) is submitted again by the next run of the same command.

What was submitted is kept in RUNS/.slurm/jobs.json (the job, each task's runs) beside
the script and the tasks' logs; where each group stands is read from Slurm (`squeue`,
which keeps ended jobs for the controller's MinJobAge) and from the runs' folders, which
alone say whether a run is complete. Nothing is submitted until the input is checked:
sbatch on PATH, Slurm answering `sinfo`, the partition one it lists, the runs folder
writable.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cli.runs_folder import unwritable

#: Task states in which Slurm will still run (or is running) the task.
ACTIVE = frozenset(
    {
        "PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "REQUEUED", "REQUEUE_HOLD",
        "REQUEUE_FED", "RESIZING", "SUSPENDED", "SIGNALING", "STAGE_OUT", "STOPPED",
    }
)  # fmt: skip
#: Of those, the ones that are waiting to (re)start.
WAITING = frozenset({"PENDING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED"})
RECORD = "jobs.json"
#: How often following asks squeue and reads the folders: often at first (a task that
#: fails at once is said at once), then gently for the controller over hours.
POLL_S, POLL_LATER_S, POLL_FAST_FOR_S = 5.0, 30.0, 120.0

Runner = Callable[[Sequence[str]], subprocess.CompletedProcess]


#: How long a Slurm command may take before it counts as failed (a hung controller).
COMMAND_TIMEOUT_S = 120.0


def run_command(argv: Sequence[str]) -> subprocess.CompletedProcess:
    """`argv` run to its end, its output captured; one that does not end within
    COMMAND_TIMEOUT_S is killed and returned as a failure (exit 124, why in stderr), so
    each caller handles it as it handles the command failing: asked again where that
    is retried, a clear error elsewhere, never a traceback."""
    try:
        return subprocess.run(list(argv), capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        why = f"{argv[0]} did not answer within {COMMAND_TIMEOUT_S:.0f} s"
        return subprocess.CompletedProcess(list(argv), 124, "", why)


@dataclass(frozen=True)
class SlurmOptions:
    """What goes to sbatch besides the tasks: the pass-through flags."""

    partition: str | None = None
    time: str | None = None
    account: str | None = None
    extra: tuple[str, ...] = ()


@dataclass(frozen=True)
class Task:
    """One array task: its group's label, its runs (folder names) and its command."""

    label: str
    runs: tuple[str, ...]
    argv: tuple[str, ...]


# ---------------------------------------------------------------- before submitting
def preflight(
    opts: SlurmOptions,
    folders: Sequence[Path],
    *,
    folder: str,
    flag: str,
    run: Runner = run_command,
) -> str | None:
    """Why nothing can be submitted, or None: --sbatch-args naming another cluster,
    sbatch missing, Slurm not answering, an unknown partition, one of `folders` that
    cannot be written (made when missing, once the rest is known to be right).
    `folder` says what they are and `flag` which of the caller's flags moves them ("the
    runs folder", "--runs (or --out)" for `macb reproduce`; "the data folder",
    "--data-dir" for `macb up`): each command has its own."""
    if error := sbatch_args_error(opts.extra):
        return error
    missing = [c for c in ("sbatch", "squeue", "sinfo") if shutil.which(c) is None]
    if missing:
        return (
            f"--launcher slurm: {', '.join(missing)} not found on PATH; run this on a "
            "Slurm login node (or put Slurm's commands on PATH)"
        )
    # -a: hidden partitions (and those of other groups) too, which sbatch takes by name
    got = run(["sinfo", "-a", "-h", "-o", "%R"])
    if got.returncode:
        return f"--launcher slurm: Slurm does not answer (sinfo: {got.stderr.strip()})"
    partitions = sorted({p.strip() for p in got.stdout.split() if p.strip()})
    if opts.partition is not None:
        # a list (sbatch runs the job in whichever of them can start it first)
        names = [p.strip() for p in opts.partition.split(",")]
        if unknown := [p for p in names if p not in partitions]:
            which = f" {', '.join(repr(p) for p in unknown)}" if len(names) > 1 else ""
            return (
                f"--partition {opts.partition}: no such partition{which} (sinfo lists: "
                f"{', '.join(partitions) or 'none'})"
            )
    for path in folders:
        if why := unwritable(path, make=True):  # (sbatch needs its log's folder)
            return (
                f"--launcher slurm: {folder} {path} is not writable ({why}); the job's tasks "
                f"write there: give {flag} on a filesystem the nodes share and you can write"
            )
    return None


def sbatch_args_error(extra: Sequence[str]) -> str | None:
    """Why --sbatch-args cannot be passed on, or None. -M/--clusters (--cluster) sends
    the job to another cluster, while squeue, asked without it, answers for the default
    one: every task would look gone at once and the next run would submit it again.
    Following jobs on several clusters is not supported, so it is refused, and so are
    SBATCH_CLUSTERS and SLURM_CLUSTERS in the environment, which sbatch reads as -M
    (squeue reads the second only, and then answers in another format)."""
    for word in extra:
        flag = word.split("=", 1)[0]
        if flag in ("--clusters", "--cluster") or word.startswith("-M"):
            return (
                f"--sbatch-args: {word} sends the job to another Slurm cluster, and macb "
                "follows jobs on the default cluster only (squeue would find none of its "
                "tasks); run this on a login node of that cluster instead"
            )
    for name in ("SBATCH_CLUSTERS", "SLURM_CLUSTERS"):
        if clusters := os.environ.get(name):
            return (
                f"--launcher slurm: {name}={clusters} is set, which sends the job to that "
                "Slurm cluster (as -M), and macb follows jobs on the default cluster only; "
                "unset it, or run this on a login node of that cluster"
            )
    return None


def device_error(devices: Sequence[str]) -> str | None:
    """Why the runs' devices cannot be asked of Slurm, or None. Each task gets one GPU
    (`--gres=gpu:1`) and Slurm shows it to the task alone, as its first CUDA device:
    `cuda:1` names a GPU no task can see."""
    for device in dict.fromkeys(devices):
        if device.startswith("cuda:") and device != "cuda:0":
            return (
                f"--device {device}: with --launcher slurm each task gets one GPU of its "
                "own, which it sees as cuda:0; give --device cuda"
            )
    return None


# ---------------------------------------------------------------- the job
def macb_argv() -> list[str]:
    """This `macb`, as a task on a node of the same filesystem starts it."""
    exe = Path(sys.executable).parent / "macb"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cli"]


#: What an #SBATCH line cannot carry in a path, and why. sbatch reads its directives
#: with its own parser (Slurm's src/sbatch/opt.c, `_get_argument`): whitespace ends an
#: argument unless quoted, an unquoted '#' starts a comment, a quote ('"' or "'")
#: groups characters up to its match and a backslash escapes the next character, in
#: quotes too. So a path is written in double quotes (`directive`), which carry spaces,
#: '#' and "'", and the characters below are refused before anything is submitted. '%'
#: is refused too: --output expands Slurm's filename patterns (%j, %A, ...) and
#: --chdir does in some versions, so a '%' in a folder's name would name another file.
UNSAFE_IN_DIRECTIVE = (
    ('"', "a double quote"),
    ("\\", "a backslash"),
    ("\n", "a newline"),
    ("%", "a '%' (Slurm reads %j, %A, ... in --output as filename patterns)"),
)


def directive(flag: str, value: str) -> str:
    """`#SBATCH --flag=value`, the value in double quotes when it holds whitespace, '#'
    or a quote, which sbatch's directive parser would otherwise split the argument at
    or read as a comment or a quote (UNSAFE_IN_DIRECTIVE: what it cannot carry at all)."""
    if any(c.isspace() or c in "#'" for c in value):
        value = f'"{value}"'
    return f"#SBATCH --{flag}={value}"


def directive_path_error(paths: Sequence[tuple[str, Path, str]]) -> str | None:
    """Why one of `paths` (what it is, the path, what to do instead) cannot be written
    in the job script's #SBATCH lines, naming it and the character; or None."""
    for what, path, instead in paths:
        for char, name in UNSAFE_IN_DIRECTIVE:
            if char in str(path):
                return (
                    f"--launcher slurm: {what} {str(path)!r} holds {name}, which the job "
                    f"script's #SBATCH --output/--chdir lines cannot carry; {instead}"
                )
    return None


def render_script(
    name: str,
    tasks: Sequence[Task],
    log_dir: Path,
    cwd: Path,
    cpus: int,
    opts: SlurmOptions,
    gpu: bool = False,
) -> str:
    """The batch script: an array of len(tasks), task i running tasks[i].argv; with
    `gpu` (the runs' device is not the CPU), each task asks for a GPU of its own."""
    lines = [
        "#!/bin/bash",
        f"#SBATCH --job-name={name}",
        f"#SBATCH --array=0-{len(tasks) - 1}",
        f"#SBATCH --cpus-per-task={cpus}",
        "#SBATCH --ntasks=1",
        "#SBATCH --requeue",
        "#SBATCH --open-mode=append",
        directive("output", f"{log_dir}/%A_%a.log"),
        directive("chdir", str(cwd)),
    ]
    if gpu:
        # --gres=gpu:1 rather than --gpus-per-task=1: each array task is a one-task job,
        # so per node is per task, and --gres works under select/cons_res too, where the
        # --gpus-* options are refused (they need cons_tres). Slurm sets the task's
        # CUDA_VISIBLE_DEVICES to that GPU, which the group's `cuda` then is.
        lines.append("#SBATCH --gres=gpu:1")
    lines += placement(opts)
    lines += [
        "# Written by `macb reproduce --launcher slurm`. Each task trains one run group",
        "# into the runs folder and, started again (requeue, preemption, time limit,",
        "# a later submission), resumes it from its newest cut.",
        "set -euo pipefail",
        'echo "task $SLURM_ARRAY_TASK_ID on $(hostname) at $(date -u +%FT%TZ), restart '
        '${SLURM_RESTART_COUNT:-0}"',
        'case "$SLURM_ARRAY_TASK_ID" in',
    ]
    for i, t in enumerate(tasks):
        lines.append(f"  {i}) exec {shlex.join(t.argv)} ;;  # {t.label}")
    lines += ['  *) echo "no task $SLURM_ARRAY_TASK_ID" >&2; exit 2 ;;', "esac", ""]
    return "\n".join(lines)


def placement(opts: SlurmOptions) -> list[str]:
    """The #SBATCH lines of the user's partition, time limit and account (those given)."""
    given = (("partition", opts.partition), ("time", opts.time), ("account", opts.account))
    return [f"#SBATCH --{flag}={value}" for flag, value in given if value]


def sbatch_argv(opts: SlurmOptions, script: Path) -> list[str]:
    return ["sbatch", "--parsable", *opts.extra, str(script)]


def parse_job_id(stdout: str) -> str:
    """The job id of `sbatch --parsable` ('123' or '123;cluster')."""
    text = stdout.strip().splitlines()[-1] if stdout.strip() else ""
    job = text.split(";")[0].strip()
    if not job.isdigit():
        raise ValueError(f"sbatch printed no job id: {stdout!r}")
    return job


# ---------------------------------------------------------------- what Slurm says
@dataclass(frozen=True)
class TaskState:
    state: str  # Slurm's, e.g. RUNNING, PENDING, CANCELLED
    reason: str = ""  # Slurm's reason for a pending task (e.g. BeginTime, Resources)
    name: str | None = None  # the job's name (None: not asked)


def squeue_argv() -> list[str]:
    """This user's tasks, ended ones too, one line per array task."""
    import pwd

    user = pwd.getpwuid(os.getuid()).pw_name
    return ["squeue", "-u", user, "-h", "-r", "-t", "all", "-o", "%i|%T|%r|%j"]


def parse_squeue(text: str) -> dict[str, TaskState]:
    """`squeue -h -r -o '%i|%T|%r|%j'` lines as {'JOB_INDEX': state} (a job that is no
    array under its own id; the name, last, may hold '|')."""
    out: dict[str, TaskState] = {}
    for line in text.splitlines():
        parts = line.strip().split("|")
        if len(parts) < 2 or not parts[0]:
            continue
        reason = parts[2].strip() if len(parts) > 2 else ""
        name = "|".join(parts[3:]).strip() if len(parts) > 3 else None
        state = parts[1].strip().split()[0]
        out[parts[0].strip()] = TaskState(state, "" if reason == "None" else reason, name)
    return out


def query(run: Runner = run_command) -> dict[str, TaskState]:
    """Every task of this user's jobs that the controller still knows."""
    got = run(squeue_argv())
    if got.returncode:
        raise RuntimeError(f"squeue failed: {got.stderr.strip()}")
    return parse_squeue(got.stdout)


# ---------------------------------------------------------------- the record
def record_path(runs_dir: Path) -> Path:
    return runs_dir / ".slurm" / RECORD


def load_record(runs_dir: Path) -> list[dict[str, Any]]:
    path = record_path(runs_dir)
    if not path.exists():
        return []
    return list(json.loads(path.read_text()).get("submissions", []))


def save_record(runs_dir: Path, submissions: list[dict[str, Any]]) -> None:
    path = record_path(runs_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"submissions": submissions}, indent=1) + "\n")
    tmp.replace(path)


# ---------------------------------------------------------------- where groups stand
@dataclass
class GroupState:
    """A submitted group as it stands: complete (every run's folder says so), running,
    pending, or incomplete (Slurm no longer runs it and some run is unfinished)."""

    label: str
    task: str  # JOB_INDEX
    runs: list[str]
    status: str
    slurm: TaskState | None = None  # what Slurm says of the task, while it knows it
    episodes: tuple[int, int] = (0, 0)  # the group's least episode, its target

    def said(self) -> str:
        """Slurm's words where they add to the status: why a task waits (a requeued
        one's state and reason), the state an incomplete one ended in."""
        s = self.slurm
        if self.status == "pending" and s:
            return ", ".join(w for w in (s.state if s.state != "PENDING" else "", s.reason) if w)
        if self.status == "incomplete":
            return s.state if s else "no longer known to Slurm"
        return ""

    def line(self) -> str:
        ep, target = self.episodes
        how = f" ({said})" if (said := self.said()) else ""
        text = f"{self.label} [job {self.task}]: {self.status}{how}, episode {ep:,} of {target:,}"
        if self.status == "incomplete":
            text += "; runs: " + ", ".join(self.runs)
        return text


@dataclass
class Standing:
    groups: list[GroupState] = field(default_factory=list)

    def of(self, status: str) -> list[GroupState]:
        return [g for g in self.groups if g.status == status]

    @property
    def active(self) -> bool:
        return any(g.status in ("running", "pending") for g in self.groups)

    def summary(self) -> str:
        counts = {s: len(self.of(s)) for s in ("running", "pending", "incomplete", "complete")}
        return ", ".join(f"{n} {s}" for s, n in counts.items() if n)


def standing(
    submissions: list[dict[str, Any]],
    slurm: dict[str, TaskState],
    done: Callable[[str], bool],
    progress: Callable[[str], tuple[int, int]],
    wanted: set[str] | None = None,
) -> Standing:
    """Each run's latest task (a later submission of a run supersedes an earlier one),
    judged by Slurm's state and the runs' folders. `wanted`: only tasks with such runs."""
    latest: dict[str, tuple[str, dict[str, Any]]] = {}
    sub_name: dict[str, str | None] = {}
    for sub in submissions:
        for t in sub["tasks"]:
            task_id = f"{sub['job']}_{t['index']}"
            sub_name[task_id] = sub.get("name")
            for r in t["runs"]:
                latest[r] = (task_id, t)
    seen: dict[str, GroupState] = {}
    for run, (task_id, t) in latest.items():
        if task_id in seen or (wanted is not None and run not in wanted):
            continue
        runs = [r for r in t["runs"] if latest[r][0] == task_id]
        state = slurm.get(task_id)
        if state and sub_name.get(task_id) not in (None, state.name):
            state = None  # another job of that id (a Slurm whose ids started again)
        eps = [progress(r) for r in runs]
        episodes = (min(e for e, _ in eps), max(n for _, n in eps))
        if all(done(r) for r in runs):
            status = "complete"
        elif state and state.state in ACTIVE:
            status = "pending" if state.state in WAITING else "running"
        else:
            status = "incomplete"
        seen[task_id] = GroupState(t["label"], task_id, runs, status, state, episodes)
    return Standing(list(seen.values()))


# ---------------------------------------------------------------- submit, follow
def submit(
    name: str,
    tasks: Sequence[Task],
    slurm_dir: Path,
    cpus: int,
    opts: SlurmOptions,
    run: Runner = run_command,
    gpu: bool = False,
) -> tuple[str, dict[str, Any]]:
    """One array job of `tasks` (script and logs in `slurm_dir`; `gpu`: a GPU per task):
    its id and the record of it (when, how, each task's index, label, runs and command)."""
    slurm_dir.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
    script = slurm_dir / f"{name}-{stamp}.sh"
    script.write_text(render_script(name, tasks, slurm_dir, Path.cwd(), cpus, opts, gpu))
    argv = sbatch_argv(opts, script)
    got = run(argv)
    if got.returncode:
        raise RuntimeError(f"{shlex.join(argv)} failed: {got.stderr.strip() or got.stdout}")
    job = parse_job_id(got.stdout)
    entry = {
        "job": job,
        "name": name,
        "submitted": datetime.now(UTC).isoformat(timespec="seconds"),
        "sbatch": argv,
        "logs": str(slurm_dir),
        "tasks": [
            {"index": i, "label": t.label, "runs": list(t.runs), "command": list(t.argv)}
            for i, t in enumerate(tasks)
        ],
    }
    return job, entry


def follow(
    look: Callable[[], Standing],
    total: Callable[[], tuple[int, int]],
    quiet: bool,
    each: Callable[[Standing], list[str]] | None = None,
    poll_s: float | None = None,
) -> Standing:
    """Polls until Slurm runs none of the groups: a line per group whose status changes,
    the lines `each` returns for a standing (pages built), and (unless quiet) a bar of
    the runs' episodes; the last standing."""
    bar = None
    if not quiet:
        from tqdm import tqdm

        done, target = total()
        bar = tqdm(total=target, initial=done, unit="ep", desc="episodes (all runs)")

    def say(text: str) -> None:
        if bar:
            bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr, flush=True)

    last: dict[str, str] = {}
    t0 = time.monotonic()

    def pause() -> float:
        if poll_s is not None:
            return poll_s
        return POLL_S if time.monotonic() - t0 < POLL_FAST_FOR_S else POLL_LATER_S

    try:
        while True:
            try:
                now = look()
            except RuntimeError as err:  # the controller busy or restarting: ask again
                say(f"{err}; asking again in {pause():.0f} s")
                time.sleep(pause())
                continue
            for g in now.groups:
                if last.get(g.task) != g.status:
                    last[g.task] = g.status
                    say(g.line())
            for text in each(now) if each else []:
                say(text)
            if bar:
                done, _ = total()
                bar.update(done - bar.n)
                bar.set_postfix_str(now.summary())
            if not now.active:
                return now
            time.sleep(pause())
    finally:
        if bar:
            bar.close()


def cpus_for(configs: Sequence[Any]) -> int:
    """A task's CPUs: its runs' torch threads (a group's update runs on them)."""
    return max((int(getattr(c, "threads", 1) or 1) for c in configs), default=1)


def env_note() -> str:
    """SLURM_CONF when set, for the messages (which Slurm was asked)."""
    conf = os.environ.get("SLURM_CONF")
    return f" (SLURM_CONF={conf})" if conf else ""


# ---------------------------------------------------------------- the command
def group_command(
    fig: str, profile: str, args: Any, out: Path, runs_dir: Path, names: Sequence[str]
) -> list[str]:
    """The `macb reproduce` that trains one group, `names`, of the figure the user's
    command describes (the same runs and configs: seeds, episodes, arms, precision,
    device, threads), resuming them when run again."""
    argv = [*macb_argv(), "reproduce", fig, "--local", "--profile", profile]
    if args.seeds:
        argv += ["--seeds", *map(str, args.seeds)]
    for flag in ("episodes", "precision", "device", "threads"):
        if getattr(args, flag, None) is not None:
            argv += [f"--{flag}", str(getattr(args, flag))]
    if args.arms:
        argv += ["--arms", *args.arms]
    argv += ["--out", str(out), "--runs", str(runs_dir), "--quiet", "--group-runs", *names]
    return argv


def options(args: Any) -> SlurmOptions:
    return SlurmOptions(
        args.partition, args.time, args.account, tuple(shlex.split(args.sbatch_args or ""))
    )


@dataclass(eq=False)  # one per figure, told apart by identity
class Campaign:
    """One figure of a submission: its runs (cli.local.LocalRun), where they go, and the
    body and flags that name them (each task's command repeats them)."""

    fig: Any  # cli.reproduce.defs.FigureDef
    body: dict[str, Any]
    profile: str
    out: Path
    runs_dir: Path
    runs: list[Any]
    page_built: bool = False

    @property
    def names(self) -> set[str]:
        return {r.name for r in self.runs}

    def progress(self) -> dict[str, tuple[int, int]]:
        """Each run's (episode, target), from the end of its rows only: cheap to ask
        every poll of a campaign whose files hold tens of thousands of rows."""
        from cli.reproduce.status import read_folders

        p = read_folders(self.runs, self.runs_dir, self.fig.episodes)
        return {r.run: (r.episode, r.target) for r in p.runs}

    def finished(self, eps: dict[str, tuple[int, int]]) -> Callable[[str], bool]:
        """Whether a run is complete, as cli.local.run_state says (every episode run,
        the checkpoint written; the config was checked before submitting)."""

        def done(name: str) -> bool:
            episode, target = eps.get(name, (0, 1))
            return episode >= target and (self.runs_dir / name / "checkpoint.pt").exists()

        return done

    def complete(self) -> bool:
        return all(map(self.finished(self.progress()), self.names))

    def standing(self, slurm: dict[str, TaskState]) -> Standing:
        eps = self.progress()
        return standing(
            load_record(self.runs_dir),
            slurm,
            self.finished(eps),
            lambda r: eps.get(r, (0, 0)),
            self.names,
        )

    def page(self) -> int:
        """The figure's page, once (0 when every run completed)."""
        from cli.reproduce.page import write_page

        self.page_built = True
        return write_page(self.fig, self.body, self.profile, self.out, self.runs_dir, True)


def campaign(
    fig: Any, body: dict[str, Any], profile: str, out: Path, runs: Path | None
) -> Campaign:
    from cli.local import expand_body

    out = out.resolve()
    runs_dir = (runs or out / "runs").resolve()
    return Campaign(fig, body, profile, out, runs_dir, expand_body(body)[2])


def reproduce_slurm(campaigns: list[Campaign], args: Any, slurm_dir: Path | None = None) -> int:
    """`macb reproduce FIGURE|all --local --launcher slurm`: submit, as one array job,
    the groups of runs neither complete nor in Slurm's hands; follow them (or not:
    --detach); build each figure's page once its runs are complete. 0 when every page
    is built (or, with --detach, when nothing ended unfinished), 1 while some group is
    incomplete (named), 2 when refused before submitting."""
    from cli.local import config_conflicts, plan_groups

    try:
        opts = options(args)
    except ValueError as err:  # shlex: an unclosed quote
        return _refuse(f"--sbatch-args: {err}")
    runs_dirs = [c.runs_dir for c in campaigns]
    slurm_dir = slurm_dir or campaigns[0].runs_dir / ".slurm"
    if error := directive_path_error(
        [
            ("the logs' folder", slurm_dir, "give --runs (or --out) a folder without it"),
            ("this command's folder", Path.cwd(), "run it from a folder without it"),
        ]
    ):
        return _refuse(error)
    if error := device_error([r.config.device for c in campaigns for r in c.runs]):
        return _refuse(error)
    if error := preflight(opts, runs_dirs, folder="the runs folder", flag="--runs (or --out)"):
        return _refuse(error)
    if conflicts := [line for c in campaigns for line in config_conflicts(c.runs, c.runs_dir)]:
        for line in conflicts:
            print(line, file=sys.stderr)
        return _refuse("move those folders away or give another --out: nothing was submitted")

    def look_each() -> list[tuple[Campaign, Standing]]:
        slurm = query()
        return [(c, c.standing(slurm)) for c in campaigns]

    def merged(each: list[tuple[Campaign, Standing]]) -> Standing:
        return Standing([g for _, s in each for g in s.groups])

    def look() -> Standing:
        return merged(look_each())

    def total() -> tuple[int, int]:
        eps = [e for c in campaigns for e in c.progress().values()]
        return sum(e for e, _ in eps), sum(t for _, t in eps)

    try:
        before_each = look_each()
    except RuntimeError as err:
        return _refuse(str(err))
    before = merged(before_each)
    # A run is its folder in its figure's runs folder: figures share run names (fig3's
    # and table2's beta_0.0-s0 are two runs), so what Slurm holds is told apart by both.
    held = {
        (c.runs_dir, r)
        for c, s in before_each
        for g in s.groups
        if g.status in ("running", "pending")
        for r in g.runs
    }
    tasks: list[Task] = []
    owner: list[Campaign] = []
    for c, s in before_each:
        done = c.finished(c.progress())
        todo = [r for r in c.runs if (c.runs_dir, r.name) not in held and not done(r.name)]
        again = {r.name for r in todo}
        for g in s.of("incomplete"):
            n = sum(r in again for r in g.runs)
            print(f"{g.line()}: submitting its {n} unfinished run(s) again", file=sys.stderr)
        if not todo:
            continue
        # sized as on the CPU whatever the device (default: this machine's CPUs), not by
        # the GPUs of this login node: each task gets a GPU of its own from Slurm
        jobs = args.jobs or os.cpu_count() or 1
        plan = plan_groups(todo, c.runs_dir, args.group_size, jobs)
        for i, (state, members) in enumerate(plan, 1):
            chosen = [todo[m] for m in members]
            task = chosen[0].config.task
            label = f"{c.fig.name} group {i}/{len(plan)} ({len(chosen)} runs: {task})"
            print(f"{label}: {'resumes from ' + state if state != 'new' else 'starts'}",
                  file=sys.stderr)  # fmt: skip
            names = [r.name for r in chosen]
            argv = group_command(c.fig.name, c.profile, args, c.out, c.runs_dir, names)
            tasks.append(Task(label, tuple(names), tuple(argv)))
            owner.append(c)
    job: str | None = None
    if tasks:
        name = "macb-" + "-".join(dict.fromkeys(c.fig.name for c in owner))
        cpus = cpus_for([r.config for c in campaigns for r in c.runs])
        gpu = any(r.config.device != "cpu" for c in owner for r in c.runs)
        try:
            job, entry = submit(name[:64], tasks, slurm_dir, cpus, opts, gpu=gpu)
        except (RuntimeError, ValueError, OSError) as err:
            return _refuse(str(err))
        for c in dict.fromkeys(owner):  # each figure records its own tasks
            mine = [t for t, o in zip(entry["tasks"], owner) if o is c]
            save_record(c.runs_dir, [*load_record(c.runs_dir), {**entry, "tasks": mine}])
        print(f"submitted job {job}{env_note()}: {len(tasks)} task(s), logs in "
              f"{slurm_dir}/{job}_<task>.log", file=sys.stderr)  # fmt: skip
    elif before.active:
        print("every unfinished run is in Slurm's hands already", file=sys.stderr)

    codes: list[int] = []

    def pages(now: Standing) -> list[str]:
        built = []
        for c in campaigns:
            if not c.page_built and c.complete():
                codes.append(c.page())
                built.append(f"{c.fig.name}: complete, its page is in {c.out}")
        return built

    if args.detach:
        try:
            now = look()
        except RuntimeError as err:  # the job is in; only its standing is not known yet
            what = f"job {job} was submitted" if job else "nothing was submitted"
            print(f"{what}; where the groups stand is unknown ({err}): the same command "
                  "again says", file=sys.stderr)  # fmt: skip
            return 0
        for g in now.groups:
            print(g.line(), file=sys.stderr)
        pages(now)
        if now.active:
            print(
                f"{now.summary()}; the same command again reports, and builds each page once "
                "its figure's groups are complete",
                file=sys.stderr,
            )
    else:
        try:
            now = follow(look, total, args.quiet, pages)
        except KeyboardInterrupt:
            print(
                "stopped following; the tasks go on in Slurm (scancel to stop them), and "
                "the same command again reports where they stand",
                file=sys.stderr,
            )
            return 130
    missing = now.of("incomplete")
    for g in missing:
        print(g.line(), file=sys.stderr)
    if missing:
        print(
            f"{len(missing)} group(s) incomplete (their logs: {slurm_dir}); the same command "
            "again submits them again and resumes their runs from their cuts",
            file=sys.stderr,
        )
        return 1
    return max(codes, default=0)


def _refuse(msg: str) -> int:
    print(f"macb reproduce: {msg}", file=sys.stderr)
    return 2
