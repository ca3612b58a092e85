"""`--launcher slurm`'s logic without a Slurm (tests/test_slurm.py runs it on a real
one): the batch script, what squeue and sbatch print read back, where each group
stands, the checks before anything is submitted, and each task's command naming the
same runs as the user's."""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
from pathlib import Path

import pytest

from cli.reproduce import slurm
from cli.reproduce.slurm import SlurmOptions, Task, TaskState


@pytest.fixture(scope="module")
def reproduce_parser() -> argparse.ArgumentParser:
    saved = dict(os.environ)  # importing cli sets thread variables; keep them out
    try:
        from cli.main import build_parser
    finally:
        os.environ.clear()
        os.environ.update(saved)
    (sub,) = (a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["reproduce"]


def test_the_script_runs_each_task_s_own_command_with_its_words_intact(tmp_path):
    tasks = [
        Task("group 1/2", ("a-s0",), ("printf", "%s|", "one", "it's a b")),
        Task("group 2/2", ("b-s0", "c-s0"), ("printf", "%s|", "two", "*", "$HOME")),
    ]
    opts = SlurmOptions("short", "02:00:00", "lab")
    text = slurm.render_script("macb-fig3", tasks, tmp_path / "logs", tmp_path, 2, opts)
    for line in ("--array=0-1", "--cpus-per-task=2", "--requeue", "--open-mode=append",
                 "--partition=short", "--time=02:00:00", "--account=lab",
                 f"--output={tmp_path}/logs/%A_%a.log"):  # fmt: skip
        assert f"#SBATCH {line}\n" in text, line
    script = tmp_path / "job.sh"
    script.write_text(text)
    for index, words in [("0", "one|it's a b|"), ("1", "two|*|$HOME|")]:
        env = {"PATH": os.environ["PATH"], "SLURM_ARRAY_TASK_ID": index, "HOME": "/h"}
        got = subprocess.run(["bash", str(script)], capture_output=True, text=True, env=env)
        assert got.returncode == 0, got.stderr
        assert got.stdout.splitlines()[-1] == words
    env = {"PATH": os.environ["PATH"], "SLURM_ARRAY_TASK_ID": "7"}
    assert subprocess.run(["bash", str(script)], env=env, capture_output=True).returncode == 2
    bare = slurm.render_script("j", tasks[:1], tmp_path, tmp_path, 1, SlurmOptions())
    assert "--partition" not in bare and "--time" not in bare and "--array=0-0" in bare


def test_what_sbatch_and_squeue_print_is_read_back():
    assert slurm.parse_job_id("4711\n") == "4711"
    assert slurm.parse_job_id("4711;cluster2\n") == "4711"
    with pytest.raises(ValueError, match="no job id"):
        slurm.parse_job_id("sbatch: error: Batch job submission failed\n")
    assert slurm.sbatch_argv(SlurmOptions(extra=("--qos=long", "--mem", "4G")), Path("s.sh")) == [
        "sbatch", "--parsable", "--qos=long", "--mem", "4G", "s.sh",
    ]  # fmt: skip
    text = ("12_0|RUNNING|None|macb-fig3\n12_1|PENDING|BeginTime|macb-fig3\n"
            "13|COMPLETED|None|a|b\n\n12_2|CANCELLED|None|macb-fig3\n14|RUNNING\n")  # fmt: skip
    assert slurm.parse_squeue(text) == {
        "12_0": TaskState("RUNNING", "", "macb-fig3"),
        "12_1": TaskState("PENDING", "BeginTime", "macb-fig3"),
        "13": TaskState("COMPLETED", "", "a|b"),
        "12_2": TaskState("CANCELLED", "", "macb-fig3"),
        "14": TaskState("RUNNING"),
    }


def _submission(job: str, *groups: tuple[str, ...]) -> dict:
    tasks = [{"index": i, "label": f"g{job}.{i}", "runs": list(g)} for i, g in enumerate(groups)]
    return {"job": job, "tasks": tasks}


def test_each_group_stands_where_slurm_and_its_runs_folders_say():
    subs = [_submission("7", ("a", "b"), ("c",), ("d",), ("e",), ("f",))]
    states = {
        "7_0": TaskState("CANCELLED"),  # but its runs completed: complete
        "7_1": TaskState("RUNNING"),
        "7_2": TaskState("PENDING", "BeginTime"),  # requeued, waiting to start again
        "7_3": TaskState("TIMEOUT"),
        # 7_4: forgotten by the controller, its run unfinished
    }
    done = {"a", "b"}
    s = slurm.standing(subs, states, done.__contains__, lambda r: (3, 10))
    got = {g.task: g.status for g in s.groups}
    assert got == {"7_0": "complete", "7_1": "running", "7_2": "pending",
                   "7_3": "incomplete", "7_4": "incomplete"}  # fmt: skip
    assert s.active and s.summary() == "1 running, 1 pending, 2 incomplete, 1 complete"
    lines = {g.task: g.line() for g in s.groups}
    assert lines["7_2"] == "g7.2 [job 7_2]: pending (BeginTime), episode 3 of 10"
    assert lines["7_3"] == "g7.3 [job 7_3]: incomplete (TIMEOUT), episode 3 of 10; runs: e"
    assert "no longer known to Slurm" in lines["7_4"] and lines["7_4"].endswith("runs: f")
    # A later submission of a run supersedes the earlier task; `wanted` keeps one figure's.
    subs.append(_submission("9", ("e", "f")))
    s = slurm.standing(subs, {**states, "9_0": TaskState("RUNNING")}, done.__contains__,
                       lambda r: (0, 10), wanted={"c", "d", "e", "f"})  # fmt: skip
    assert {g.task: (g.status, g.runs) for g in s.groups} == {
        "7_1": ("running", ["c"]),
        "7_2": ("pending", ["d"]),
        "9_0": ("running", ["e", "f"]),
    }
    ended = slurm.standing(subs[:1], {}, lambda r: True, lambda r: (10, 10))
    assert not ended.active and ended.summary() == "5 complete"
    # A task of another job that has the recorded id (ids started again) is not ours.
    named = [{**subs[1], "name": "macb-fig3"}]
    other = {"9_0": TaskState("RUNNING", "", "someone-else")}
    (g,) = slurm.standing(named, other, done.__contains__, lambda r: (0, 10)).groups
    assert g.status == "incomplete" and "no longer known to Slurm" in g.line()
    requeued = {"9_0": TaskState("REQUEUE_HOLD", "JobHeldAdmin", "macb-fig3")}
    (g,) = slurm.standing(named, requeued, done.__contains__, lambda r: (0, 10)).groups
    assert g.line() == "g9.0 [job 9_0]: pending (REQUEUE_HOLD, JobHeldAdmin), episode 0 of 10"


class FakeSlurm:
    def __init__(self, partitions: str = "short\nlong\n", rc: int = 0) -> None:
        self.partitions, self.rc, self.calls = partitions, rc, []

    def __call__(self, argv):
        self.calls.append(list(argv))
        err = "slurm_load_partitions: Unable to contact slurm controller" if self.rc else ""
        return subprocess.CompletedProcess(argv, self.rc, self.partitions, err)


def test_nothing_is_submitted_on_bad_input(tmp_path, monkeypatch):
    runs = tmp_path / "out" / "runs"

    def preflight(opts: SlurmOptions, folders: list[Path], run: FakeSlurm) -> str | None:
        return slurm.preflight(opts, folders, folder="the runs folder", flag="--runs", run=run)

    monkeypatch.setattr(slurm.shutil, "which", lambda c: None if c == "sbatch" else "/bin/" + c)
    fake = FakeSlurm()
    assert "sbatch not found on PATH" in preflight(SlurmOptions(), [runs], fake)
    assert fake.calls == [] and not runs.exists()
    monkeypatch.setattr(slurm.shutil, "which", lambda c: "/bin/" + c)
    why = preflight(SlurmOptions(partition="gpu"), [runs], fake)
    assert why == "--partition gpu: no such partition (sinfo lists: long, short)"
    assert not runs.exists()  # refused before the runs folder is made
    why = preflight(SlurmOptions(), [runs], FakeSlurm(rc=1))
    assert why.startswith("--launcher slurm: Slurm does not answer (sinfo: slurm_load_partitions")
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    why = preflight(SlurmOptions(), [blocker / "runs"], fake)
    assert why.startswith(f"--launcher slurm: the runs folder {blocker / 'runs'} is not writable")
    assert preflight(SlurmOptions(partition="long"), [runs], fake) is None
    assert runs.is_dir() and list(runs.iterdir()) == []  # made; the probe file removed


@pytest.mark.parametrize(
    "command, folder, flag, wrong",
    [
        (["reproduce", "fig3", "--local", "--episodes", "2", "--out"], "the runs folder",
         "--runs (or --out)", "--data-dir"),
        (["up", "--data-dir"], "the data folder", "--data-dir", "--runs"),
    ],
)  # fmt: skip
def test_an_unwritable_folder_is_named_with_the_flag_that_moves_it(
    tmp_path, command, folder, flag, wrong
):
    """Each command that submits to Slurm names its own flag for the folder the job's tasks
    write to (`macb up` once told the user to give --runs or --out, flags it has not in that
    meaning). Slurm's commands stubbed on PATH, so the check gets as far as the folder."""
    from tests.harness import macb

    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name, text in (("sbatch", ""), ("squeue", ""), ("sinfo", "echo short\n")):
        (stubs / name).write_text(f"#!/bin/sh\n{text}exit 0\n")
        (stubs / name).chmod(0o755)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    path = f"{stubs}{os.pathsep}{os.environ.get('PATH', '')}"
    got = macb(*command, str(blocker / "d"), "--launcher", "slurm", env={"PATH": path})
    assert got.returncode == 2, got.stderr
    (line,) = got.stderr.strip().splitlines()
    assert line.startswith(f"macb {command[0]}: --launcher slurm: {folder} "), line
    assert "is not writable (Not a directory)" in line and f"give {flag} on a " in line, line
    assert wrong not in line, line


@pytest.mark.parametrize(
    "flags",
    [
        [],
        ["--seeds", "4", "5", "--episodes", "9", "--precision", "bf16", "--threads", "2"],
        ["--device", "cuda", "--episodes", "9"],
        ["--arms", "beta=0.8", "CONSTANT beta=0.8*", "--profile", "thesis"],
    ],
)
def test_each_task_s_command_names_the_runs_and_configs_of_the_user_s(
    reproduce_parser, tmp_path, flags
):
    from cli.local import expand_body
    from cli.reproduce.experiments import experiment_body, select_arms
    from cli.reproduce.figures import FIGURES

    def runs_of(args):
        fig = FIGURES[args.figure]
        body = experiment_body(fig, args.profile, args.seeds or [0, 1, 2], args.episodes,
                               args.precision)  # fmt: skip
        body = select_arms(fig, body, args.arms) if args.arms else body
        if args.threads is not None:
            body["threads"] = args.threads
        if args.device is not None:
            body["device"] = args.device
        return {r.name: r.config for r in expand_body(body)[2]}

    user = reproduce_parser.parse_args(["fig3", "--local", "--launcher", "slurm", *flags])
    mine = runs_of(user)
    names = sorted(mine)[:2]
    argv = slurm.group_command("fig3", user.profile, user, tmp_path, tmp_path / "r", names)
    words = shlex.split(shlex.join(argv))  # through the script's shell quoting
    task = reproduce_parser.parse_args(words[words.index("reproduce") + 1 :])
    assert task.local and task.launcher == "local" and task.group_runs == names
    assert Path(task.runs) == tmp_path / "r" and Path(task.out) == tmp_path
    assert runs_of(task) == mine


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--launcher", "slurm"], "--launcher slurm: give --local"),
        (["--local", "--partition", "short"], "--partition is for --launcher slurm"),
        (["--local", "--detach"], "--detach is for --launcher slurm"),
        (["--group-runs", "x-s0"], "--group-runs trains with --local"),
        (["--local", "--group-runs", "nosuch-s0"], "--group-runs: no run nosuch-s0 in"),
        # (--status went first and wrote no page)
        (["--status", "--report-only"], "--status and --report-only: give one"),
    ],
)
def test_launcher_flags_that_do_not_fit_are_refused(
    reproduce_parser, tmp_path, flags, message, capsys
):
    args = reproduce_parser.parse_args(["fig3", "--episodes", "2", "--out", str(tmp_path), *flags])
    assert args.func(args) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--local"], "all: give --local --launcher slurm (or name one figure)"),
        (["--local", "--launcher", "slurm", "--arms", "x*"], "all: --arms is for one figure"),
        (["--local", "--launcher", "slurm", "--runs", "r"], "all: --runs is for one figure"),
    ],
)
def test_all_is_every_figure_on_slurm_and_refuses_one_figure_s_flags(
    reproduce_parser, tmp_path, flags, message, capsys
):
    args = reproduce_parser.parse_args(["all", "--out", str(tmp_path / "o"), *flags])
    assert args.func(args) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_following_says_each_change_once_survives_a_silent_controller_and_ends(capsys):
    from cli.reproduce.slurm import GroupState, Standing

    def at(status: str) -> Standing:
        return Standing([GroupState("fig3 group 1/1", "5_0", ["a-s0"], status, "", (0, 6))])

    seen = iter([at("pending"), at("pending"), RuntimeError("squeue failed: timeout"),
                 at("running"), at("complete")])  # fmt: skip

    def look() -> Standing:
        item = next(seen)
        if isinstance(item, Exception):
            raise item
        return item

    pages = lambda now: ["page built"] if not now.active else []  # noqa: E731
    last = slurm.follow(look, lambda: (0, 6), quiet=True, each=pages, poll_s=0)
    assert last.of("complete") and not last.active
    assert capsys.readouterr().err.splitlines() == [
        "fig3 group 1/1 [job 5_0]: pending, episode 0 of 6",
        "squeue failed: timeout; asking again in 0 s",
        "fig3 group 1/1 [job 5_0]: running, episode 0 of 6",
        "fig3 group 1/1 [job 5_0]: complete, episode 0 of 6",
        "page built",
    ]


# ---------------------------------------------------------------- the #SBATCH lines
def sbatch_reads(script: str) -> list[str]:
    """The arguments sbatch takes from a script's #SBATCH lines: Slurm's own directive
    parser (src/sbatch/opt.c, `_get_argument`) ported: whitespace ends an argument unless
    quoted, a quote groups up to its match, a backslash escapes the next character,
    an unquoted '#' starts a comment; the first line that is no comment ends them."""
    argv: list[str] = []
    for line in script.splitlines()[1:]:
        if not line.startswith("#"):
            break
        if not line.startswith("#SBATCH"):
            continue
        rest, i = line[len("#SBATCH") :], 0
        while True:
            while i < len(rest) and rest[i].isspace():
                i += 1
            if i >= len(rest):
                break
            arg, quote, escaped = "", "", False
            while i < len(rest) and (quote or not rest[i].isspace()):
                c, i = rest[i], i + 1
                if escaped:
                    escaped = False
                elif c == "\\":
                    escaped = True
                    continue
                elif quote:
                    if c == quote:
                        quote = ""
                        continue
                elif c in "\"'":
                    quote = c
                    continue
                elif c == "#":
                    i = len(rest)
                    break
                arg += c
            if arg:
                argv.append(arg)
    return argv


def test_folders_with_spaces_hashes_and_quotes_reach_sbatch_whole(tmp_path):
    """A runs or data folder named 'My Runs', 'lab#2' or "it's" is one argument to sbatch:
    written unquoted, sbatch's parser cut --output and --chdir at the space and dropped the
    rest of the line at the '#'."""
    from cli.slurm_cluster import ClusterJob, render_cluster_script

    for name in ("My Runs", "lab#2", "it's here"):
        base = tmp_path / name
        tasks = [Task("g1", ("a-s0",), ("macb", "reproduce", "fig3"))]
        text = slurm.render_script("macb-fig3", tasks, base / ".slurm", base, 1, SlurmOptions())
        argv = sbatch_reads(text)
        assert f"--output={base}/.slurm/%A_%a.log" in argv, argv
        assert f"--chdir={base}" in argv, argv
        job = ClusterJob(1, 1, 1, 1, base / "data")
        argv = sbatch_reads(render_cluster_script(job, ["macb"], base, SlurmOptions("short")))
        assert f"--output={base}/data/.slurm/cluster-%j.log" in argv, argv
        assert f"--chdir={base}" in argv and "--partition=short" in argv, argv


def slurm_stubs(tmp_path: Path, squeue: str = "exit 0", sinfo: str = "echo short") -> dict:
    """sbatch, squeue and sinfo stubbed on PATH: sbatch records its arguments (a line
    each call, in SBATCH_CALLS) and prints job id 4242, then 4243, ... The environment
    to run macb in."""
    stubs = tmp_path / "bin"
    stubs.mkdir(exist_ok=True)
    calls = tmp_path / "sbatch-calls.txt"
    ids = shlex.quote(str(tmp_path / "sbatch-next-id"))
    texts = {
        "sbatch": f'echo "$@" >> {shlex.quote(str(calls))}\n'
        f"n=$(cat {ids} 2>/dev/null || echo 4242); echo $((n + 1)) > {ids}; echo $n\n",
        "squeue": squeue + "\n",
        "sinfo": sinfo + "\n",
    }
    for name, text in texts.items():
        (stubs / name).write_text(f"#!/bin/bash\n{text}")
        (stubs / name).chmod(0o755)
    return {"PATH": f"{stubs}{os.pathsep}{os.environ.get('PATH', '')}", "SBATCH_CALLS": str(calls)}


@pytest.mark.parametrize(
    "command, folder, char",
    [
        (["reproduce", "fig3", "--local", "--episodes", "2", "--out"], "50%", "'%'"),
        (["reproduce", "fig3", "--local", "--episodes", "2", "--out"], 'say "hi"', "double quote"),
        (["up", "--data-dir"], "back\\slash", "backslash"),
    ],
)  # fmt: skip
def test_a_folder_the_sbatch_lines_cannot_carry_is_refused_naming_it(
    tmp_path, command, folder, char
):
    from tests.harness import macb

    env = slurm_stubs(tmp_path)
    path = tmp_path / folder
    got = macb(*command, str(path), "--launcher", "slurm", env=env)
    assert got.returncode == 2, got.stderr
    (line,) = got.stderr.strip().splitlines()
    assert repr(str(path))[:-1] in line and char in line and "#SBATCH" in line, line
    assert not Path(env["SBATCH_CALLS"]).exists() and not path.exists()


def test_detach_after_a_submission_squeue_cannot_answer_says_so_and_exits_0(tmp_path):
    """squeue answering before the submission and failing right after it (a busy
    controller): --detach once ended in a traceback, the job submitted; now it says the
    job was submitted, that where it stands is unknown and that the same command says."""
    from tests.harness import macb

    asked = tmp_path / "squeue-asked"
    squeue = (
        f"if [[ -e {asked} ]]; then echo 'squeue: error: Socket timed out' >&2; exit 1; fi\n"
        f"touch {asked}; exit 0"
    )
    env = slurm_stubs(tmp_path, squeue=squeue)
    out = str(tmp_path / "out")
    got = macb("reproduce", "fig3", "--local", "--launcher", "slurm", "--episodes", "2",
               "--seeds", "0", "--out", out, "--detach", "--quiet", env=env)  # fmt: skip
    assert got.returncode == 0, got.stderr
    assert "Traceback" not in got.stderr, got.stderr
    last = got.stderr.strip().splitlines()[-1]
    assert last.startswith("job 4242 was submitted; where the groups stand is unknown"), last
    assert "Socket timed out" in last and "the same command again says" in last, last
    assert len(Path(env["SBATCH_CALLS"]).read_text().splitlines()) == 1


@pytest.mark.parametrize(
    "extra", [("--clusters=gpu",), ("-M", "gpu"), ("--mem=4G", "--cluster", "a")]
)
def test_sbatch_args_naming_another_cluster_are_refused_before_slurm_is_asked(
    tmp_path, extra, monkeypatch
):
    """sbatch -M/--clusters submits to another cluster, but squeue answers for the default
    one: every task looked gone at once, exit 1, and the next run submitted it all again."""
    monkeypatch.setattr(slurm.shutil, "which", lambda c: "/bin/" + c)
    runs = tmp_path / "runs"
    fake = FakeSlurm()
    why = slurm.preflight(SlurmOptions(extra=extra), [runs], folder="f", flag="--f", run=fake)
    assert why is not None and why.startswith("--sbatch-args: ") and "another Slurm cluster" in why
    assert [w for w in extra if w.startswith("-")][-1] in why
    assert fake.calls == [] and not runs.exists()
    ok = SlurmOptions(extra=("--cluster-constraint=fast", "--mem=4G"))
    assert slurm.preflight(ok, [runs], folder="f", flag="--f", run=fake) is None


@pytest.mark.parametrize("name", ["SLURM_CLUSTERS", "SBATCH_CLUSTERS"])
def test_a_cluster_named_in_the_environment_is_refused_as_m_is(tmp_path, monkeypatch, name):
    """sbatch reads SBATCH_CLUSTERS and SLURM_CLUSTERS as -M: set on the login node, the
    job went to that cluster while squeue looked for its tasks elsewhere (or, reading
    SLURM_CLUSTERS itself, answered in its multi-cluster format)."""
    monkeypatch.setattr(slurm.shutil, "which", lambda c: "/bin/" + c)
    monkeypatch.setenv(name, "gpu")
    runs = tmp_path / "runs"
    fake = FakeSlurm()
    why = slurm.preflight(SlurmOptions(), [runs], folder="f", flag="--f", run=fake)
    assert why is not None and f"{name}=gpu is set" in why and "unset it" in why
    assert fake.calls == [] and not runs.exists()
    monkeypatch.setenv(name, "")
    assert slurm.preflight(SlurmOptions(), [runs], folder="f", flag="--f", run=fake) is None


@pytest.mark.parametrize("command", [["reproduce", "fig3", "--local", "--episodes", "2"], ["up"]])
def test_sbatch_args_of_one_flag_or_several_reach_sbatch_in_either_form(tmp_path, command):
    """`--sbatch-args '--mem=4G'` (one flag, no space) was refused by argparse ("expected
    one argument": a value starting with '-' read as an option); it is taken as written,
    as `--sbatch-args=...` always was, and an unclosed quote is refused naming the option."""
    from tests.harness import macb

    last = f"$(( $(cat {tmp_path / 'sbatch-next-id'} 2>/dev/null || echo 4243) - 1 ))"
    tasks = " ".join(f"${{n}}_{i}'|RUNNING|None|macb-fig3'" for i in range(2))
    running = f"n={last}; printf '%s\\n' {tasks}"  # the last job's tasks, running
    env = slurm_stubs(tmp_path, squeue=running)
    calls = Path(env["SBATCH_CALLS"])
    flag = "--data-dir" if command == ["up"] else "--out"
    for i, (given, passed) in enumerate([
        (["--sbatch-args", "--mem=4G"], "--parsable --mem=4G "),
        (["--sbatch-args=--qos=long --mem=4G"], "--parsable --qos=long --mem=4G "),
        (["--sbatch-args", "--qos=long -c 2"], "--parsable --qos=long -c 2 "),
    ]):  # fmt: skip
        calls.unlink(missing_ok=True)
        where = [flag, str(tmp_path / f"d{i}")]
        got = macb(*command, *where, "--launcher", "slurm", *given, "--detach", env=env)
        assert got.returncode == 0, got.stderr
        (call,) = calls.read_text().splitlines()
        assert call.startswith(passed), (given, call)
    calls.unlink()
    got = macb(*command, *where, "--launcher", "slurm", "--sbatch-args", "--qos='long", env=env)
    assert got.returncode == 2 and "--sbatch-args: No closing quotation" in got.stderr, got.stderr
    assert not calls.exists()


def test_runs_on_a_gpu_get_a_gpu_per_task_and_as_many_tasks_as_on_the_cpu(tmp_path):
    """--device cuda once asked Slurm for no GPU, and sized the plan by the GPUs of the
    submitting machine (a login node: none, so one task for every run): each task now
    asks for a GPU of its own, and the runs make as many tasks as on the CPU."""
    from tests.harness import macb

    env = slurm_stubs(tmp_path)
    scripts = {}
    for device in ("cpu", "cuda"):
        out = tmp_path / device
        got = macb("reproduce", "fig3", "--local", "--launcher", "slurm", "--episodes", "2",
                   "--seeds", "0", "--device", device, "--out", str(out), "--detach",
                   "--quiet", env=env)  # fmt: skip
        assert "submitted job " in got.stderr, got.stderr
        call = Path(env["SBATCH_CALLS"]).read_text().splitlines()[-1]
        scripts[device] = sbatch_reads(Path(call.split()[-1]).read_text())
    assert "--gres=gpu:1" in scripts["cuda"] and "--gres=gpu:1" not in scripts["cpu"]
    tasks = min(os.cpu_count() or 1, 11)  # fig3's 11 runs of seed 0, --jobs' default
    assert f"--array=0-{tasks - 1}" in scripts["cuda"], scripts["cuda"]
    assert f"--array=0-{tasks - 1}" in scripts["cpu"], scripts["cpu"]
    sbatched = len(Path(env["SBATCH_CALLS"]).read_text().splitlines())
    out = tmp_path / "second-gpu"
    argv = ["reproduce", "fig3", "--local", "--launcher", "slurm", "--episodes", "2",
            "--seeds", "0", "--device", "cuda:1", "--out", str(out), "--detach"]  # fmt: skip
    got = macb(*argv, env=env)
    # a task sees its one GPU as cuda:0, so cuda:1 would fail on every node
    assert got.returncode == 2 and "--device cuda:1: with --launcher slurm" in got.stderr
    assert "give --device cuda" in got.stderr, got.stderr
    assert len(Path(env["SBATCH_CALLS"]).read_text().splitlines()) == sbatched
    assert slurm.device_error(["cpu", "cuda", "cuda:0"]) is None


def test_all_tells_apart_runs_of_one_name_in_two_figures(tmp_path):
    """fig3 and table2 both have a run beta_0.0-s0, each in its own runs folder. What
    Slurm held was told by run name alone, so with fig3's tasks running and table2's
    cancelled, table2's beta_0.0-s0 (and every namesake) was left out of the new
    submission, though said to be submitted again."""
    import json

    from tests.harness import macb

    states = tmp_path / "squeue.txt"
    env = slurm_stubs(tmp_path, squeue=f"cat {states} 2>/dev/null; exit 0")
    out = tmp_path / "out"
    argv = ["reproduce", "all", "--local", "--launcher", "slurm", "--episodes", "2",
            "--seeds", "0", "--out", str(out), "--detach", "--quiet"]  # fmt: skip
    got = macb(*argv, env=env)
    assert "submitted job 4242: " in got.stderr, got.stderr
    (table2,) = out.glob("table2-*/runs")
    lines = []
    for record in out.glob("*/runs/.slurm/jobs.json"):
        state = "CANCELLED" if record.parents[2] == table2.parent else "RUNNING"
        for t in json.loads(record.read_text())["submissions"][0]["tasks"]:
            lines.append(f"4242_{t['index']}|{state}|None|macb-fig3-fig4-fig6-fig7-fig8-table2")
    states.write_text("\n".join(lines) + "\n")
    got = macb(*argv, env=env)
    assert "submitted job 4243: " in got.stderr, got.stderr
    subs = json.loads((table2 / ".slurm" / "jobs.json").read_text())["submissions"]
    first, again = ({r for t in s["tasks"] for r in t["runs"]} for s in subs)
    assert "beta_0.0-s0" in first and again == first
    said = [line for line in got.stderr.splitlines() if "submitting its" in line]
    assert len(said) == len(subs[0]["tasks"]) and all(line.startswith("table2 ") for line in said)
    n = sum(int(line.split("submitting its ")[1].split()[0]) for line in said)
    assert n == len(first), said


def test_a_list_of_partitions_and_hidden_ones_are_taken(tmp_path, monkeypatch):
    """sbatch takes `--partition short,long` (the first that can start the job) and a
    hidden partition by name; both were refused: the list as one unknown name, the hidden
    one because plain `sinfo` does not list it (`sinfo -a` does)."""
    monkeypatch.setattr(slurm.shutil, "which", lambda c: "/bin/" + c)

    def sinfo(argv):
        names = "short\nlong\n" + ("hidden\n" if "-a" in argv else "")
        return subprocess.CompletedProcess(argv, 0, names, "")

    def check(partition: str) -> str | None:
        opts = SlurmOptions(partition=partition)
        return slurm.preflight(opts, [tmp_path / "r"], folder="f", flag="--f", run=sinfo)

    assert check("short,long") is None and check("hidden") is None
    assert check("long,hidden") is None
    assert check("short,gpu") == (
        "--partition short,gpu: no such partition 'gpu' (sinfo lists: hidden, long, short)"
    )
    assert check("short,") is not None  # an empty name is no partition either


def test_a_slurm_command_that_hangs_is_a_failure_not_a_traceback(tmp_path, monkeypatch):
    """A hung controller makes sinfo or squeue hang: run_command's timeout raised
    TimeoutExpired through every caller. Now it is that command failing: preflight
    says Slurm does not answer, and following asks squeue again."""
    from cli.slurm_cluster import SlurmUnanswered, job_state

    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name in ("sbatch", "squeue", "sinfo"):
        (stubs / name).write_text("#!/bin/sh\nexec sleep 30\n")
        (stubs / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{stubs}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(slurm, "COMMAND_TIMEOUT_S", 0.3)
    why = slurm.preflight(SlurmOptions(), [tmp_path / "r"], folder="f", flag="--f")
    assert why == "--launcher slurm: Slurm does not answer (sinfo: sinfo did not answer within 0 s)"
    with pytest.raises(RuntimeError, match="squeue did not answer"):
        slurm.query()
    with pytest.raises(SlurmUnanswered, match=r"squeue failed 2 times \(squeue did not answer"):
        job_state("77", tries=2, pause_s=0)
