"""`macb reproduce FIGURE`: one of the thesis's figures, every arm and seed, as one
experiment through the API, then FIGURE.png / FIGURE.md / FIGURE.csv.gz beside the thesis.

When no API answers at --api, it starts the local cluster the way `macb up --run` does
(cli.cluster.local_cluster) and stops it at the end; one learner, so runs go one after
another. Resumable: the experiment's name is fixed by the figure, profile, length, seeds
and the arms' configs (cli/reproduce/experiments.py), so the same command finds it in the
store again and queues only the runs that did not complete (POST /experiments/{id}/retry);
completed runs and their points are kept.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from cli.config_flags import HelpFormatter
from cli.local import add_group_flags, group_flag_error
from cli.reproduce.defs import FigureDef
from cli.reproduce.experiments import every_arms_runs, figure_body
from cli.reproduce.figures import FIGURES, PROFILES
from cli.reproduce.page import write_page
from cli.reproduce.session import Session, answers_at, with_local_cluster
from shared.persist.files import data_dir_help
from shared.settings import settings


def add_reproduce_parser(sub: argparse._SubParsersAction) -> None:
    rp = sub.add_parser(
        "reproduce",
        help="run one of the thesis's figures (every arm x seed) and compare with the thesis",
        description="Run FIGURE's arms (its config files under configs/: configs/FIGURE/*.yaml, "
        "their constant-bonus controls among them; fig7 reuses fig4's and fig6's) over its "
        "seeds as one experiment through the API (starting the local cluster when no API "
        "answers), then write OUT/FIGURE.png (the arms overlaid, smoothed, mean over seeds, "
        "a std band), OUT/FIGURE.md (the thesis's claims beside the measured numbers, a "
        "verdict each) and OUT/FIGURE.csv.gz. Running the same command again resumes: only "
        "the runs that did not complete run again.",
        formatter_class=HelpFormatter,
    )
    rp.add_argument(
        "figure",
        metavar="FIGURE",
        choices=[*FIGURES, "all"],
        help=", ".join(FIGURES) + "; or all (with --local --launcher slurm: every figure's "
        "groups in one submission, each in OUT/FIGURE-PROFILE, OUT default runs/reproduce)",
    )
    rp.add_argument(
        "--seeds", type=int, nargs="+", metavar="SEED", help="default: the files' (0 1 2)"
    )
    rp.add_argument("--profile", choices=PROFILES, default="mpe2", help="the config profile")
    rp.add_argument("--episodes", type=int, metavar="N", help="cut every run to N episodes")
    rp.add_argument(
        "--arms",
        nargs="+",
        metavar="PATTERN",
        help="only the arms whose name matches a PATTERN (shell-style, any case; e.g. "
        "'Sparse*' for fig8's sparse arms and their control); the page says the others "
        "have no points. A later run of all arms reuses the runs these complete (--local)",
    )
    rp.add_argument(
        "--precision",
        choices=("fp32", "bf16"),
        help="every run's learner precision (default: the files', fp32). bf16 makes the "
        "learner 1.7-2.5x faster; its learning is not shown equal to fp32's "
        "(docs/performance.md, 'bf16', Learning parity)",
    )
    rp.add_argument(
        "--device",
        metavar="DEVICE",
        help="every run's learner device: cpu (the default), cuda, cuda:N, xpu, mps. With "
        "--local, --jobs defaults to one group per GPU, and a bare `cuda` gives each "
        "group's process a GPU of its own (with --launcher slurm: --jobs defaults as on the "
        "CPU, and each task asks Slurm for a GPU). The replay's rows live on the device; acting, "
        "sampling and counting stay on the CPU; "
        "a run's rows on a GPU are not the CPU's bit for bit (docs/performance.md, 'On a GPU')",
    )
    rp.add_argument(
        "--out",
        metavar="DIR",
        help="default: runs/reproduce/FIGURE-PROFILE (-bf16 in bf16, -DEVICE off the CPU)",
    )
    rp.add_argument(
        "--api",
        metavar="URL",
        help="API base URL (default: MACB_API_URL or http://127.0.0.1:8000); when none "
        "answers there, a local cluster is started with its API on that port",
    )
    rp.add_argument("--data-dir", help=data_dir_help("the local cluster's data dir"))
    rp.add_argument(
        "--slots",
        type=int,
        default=1,
        metavar="N",
        help="the local cluster serves N runs, or run groups, at once (see `macb up --slots`)",
    )
    rp.add_argument("--endpoint", default="tcp/127.0.0.1:7447", help="its router endpoint")
    rp.add_argument(
        "--interleave",
        choices=("lockstep", "async"),
        default="lockstep",
        help="through the cluster: lockstep (the thesis's loop, each run's rows those of "
        "`macb train`) or async (actors collect episodes with weights an episode or two "
        "old; faster, another interleaving: docs/fidelity.md)",
    )
    rp.add_argument(
        "--local",
        action="store_true",
        help="no API or cluster: train the figure's runs in this process as run groups "
        "(runs of one task and network train as one, each giving the rows it gives "
        "alone; the thesis's step-by-step loop), each in OUT/runs/<arm>-s<seed>/; the "
        "same command again continues from each run's last cut (docs/reliability.md, 'Campaigns')",
    )
    add_group_flags(
        rp,
        cluster="; through the local cluster this command starts: at most N runs per run "
        "group (default: the figure's runs split over --slots; see `macb up --group-size`)",
    )
    rp.add_argument(
        "--threads",
        type=int,
        metavar="N",
        help="every run's torch threads (a group's update runs on them; default the files', 1)",
    )
    rp.add_argument(
        "--runs",
        metavar="DIR",
        help="--local / --report-only: where the runs' folders are (default OUT/runs), so "
        "a page can be written elsewhere (e.g. docs/results/FIGURE-PROFILE) from stored runs",
    )
    rp.add_argument(
        "--report-only",
        action="store_true",
        help="train nothing: rebuild OUT/FIGURE.png/.md/.csv.gz from the runs a --local "
        "reproduce stored in OUT/runs/",
    )
    rp.add_argument(
        "--status",
        action="store_true",
        help="train nothing: print each run's episode of its target, its speed over the "
        "last hour of its own clock and the figure's projected finish, from the runs a "
        "--local reproduce stores in OUT/runs/ (or --runs; give the same --profile, "
        "--arms, --episodes as the run). Reads the folders only: safe while it trains",
    )
    rp.add_argument(
        "--launcher",
        choices=("local", "slurm"),
        default="local",
        help="--local: where the run groups train: in this process tree (local) or as the "
        "tasks of one Slurm array job, one group each, writing to the runs folder on a "
        "filesystem the nodes share (slurm; followed to the end unless --detach, the same "
        "command again reports, submits again what ended unfinished, and builds the page "
        "when all are complete: docs/deploy.md, 'On a Slurm cluster')",
    )
    slurm = rp.add_argument_group("--launcher slurm")
    slurm.add_argument(
        "--partition", help="the tasks' partition, or a comma-separated list (sbatch --partition)"
    )
    slurm.add_argument("--time", metavar="LIMIT", help="each task's time limit (sbatch --time)")
    slurm.add_argument("--account", help="the account charged (sbatch --account)")
    slurm.add_argument(
        "--sbatch-args",
        metavar="ARGS",
        help="more sbatch arguments, as one string (e.g. '--qos=long --mem=4G'); not "
        "-M/--clusters: the tasks are followed on the default cluster only",
    )
    slurm.add_argument(
        "--detach",
        action="store_true",
        help="submit and return at once; the same command later says where each group stands",
    )
    rp.add_argument(
        "--group-runs",
        nargs="+",
        metavar="RUN",
        help="--local: train only these runs (their folder names) as one group and write no "
        "page: the command each Slurm task runs; run again, it resumes them from their cuts",
    )
    rp.add_argument("--quiet", action="store_true", help="no progress bar")
    rp.add_argument("--quiet-services", action="store_true", help="service logs to files only")
    rp.set_defaults(func=cmd_reproduce)


def cmd_reproduce(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from services.api.client import DEFAULT_URL, ApiClient
    from shared.config import error_text

    if args.episodes is not None and args.episodes < 1:
        return _refuse(f"--episodes {args.episodes}: give a number of episodes >= 1")
    if args.slots < 1:
        return _refuse(f"--slots {args.slots}: give a number of runs at once >= 1")
    if error := group_flag_error(args, "--threads"):
        return _refuse(error)
    if error := launcher_error(args):
        return _refuse(error)
    if args.figure == "all":
        return reproduce_all(args)
    fig = FIGURES[args.figure]
    try:
        body = figure_body(fig, args)
    except (ValueError, OSError, ValidationError) as err:
        return _refuse(error_text(err))
    out = Path(args.out or f"runs/reproduce/{out_name(fig, args)}")
    if args.status:
        from cli.local import expand_body
        from cli.reproduce.status import print_status

        _, _, runs = expand_body(body)
        runs_dir = Path(args.runs) if args.runs else out / "runs"
        return print_status(
            f"{fig.name}, profile {args.profile}",
            runs,
            runs_dir,
            fig.episodes,
            every_arms_runs(fig, args),
        )
    if args.launcher == "slurm" and not (args.report_only or args.group_runs):
        from cli.local import MetricsError
        from cli.reproduce.slurm import campaign, reproduce_slurm

        runs_at = Path(args.runs) if args.runs else None
        try:
            return reproduce_slurm([campaign(fig, body, args.profile, out, runs_at)], args)
        except MetricsError as err:  # a run's rows do not read: refused before submitting
            return _refuse(str(err))
    if args.local or args.report_only:
        return reproduce_local(fig, body, args.profile, out, args)
    url = (args.api or _env_url() or DEFAULT_URL).rstrip("/")
    probe = ApiClient(url, timeout=3.0)
    try:
        answers = answers_at(probe)
    finally:
        probe.close()
    if answers:
        print(f"using the API at {url}", file=sys.stderr)
        with ApiClient(url) as api:
            session = Session(api, fig, body, args.profile, out, args.quiet)
            try:
                return session.run()
            except KeyboardInterrupt:
                return session.interrupted()
    return with_local_cluster(args, url, fig, body, out)


def out_name(fig: FigureDef, args: argparse.Namespace) -> str:
    """FIGURE-PROFILE (-bf16 in bf16, -DEVICE off the CPU): a figure's folder under
    runs/reproduce. A run's rows depend on its precision and device, and its folder
    refuses another config's: each combination has its own."""
    suffix = f"-{args.precision}" if args.precision not in (None, "fp32") else ""
    if args.device not in (None, "cpu"):
        suffix += "-" + args.device.replace(":", "")
    return f"{fig.name}-{args.profile}{suffix}"


def reproduce_all(args: argparse.Namespace) -> int:
    """`macb reproduce all --local --launcher slurm`: every figure's groups in one Slurm
    submission, each figure in OUT/FIGURE-PROFILE (OUT: --out, default runs/reproduce),
    each page built as its figure completes."""
    from pydantic import ValidationError

    from cli.reproduce.slurm import campaign, reproduce_slurm
    from shared.config import error_text

    if not (args.local and args.launcher == "slurm") or args.status or args.report_only:
        return _refuse("all: give --local --launcher slurm (or name one figure)")
    for flag in ("arms", "runs", "group_runs"):
        if getattr(args, flag):
            return _refuse(f"all: --{flag.replace('_', '-')} is for one figure")
    parent = Path(args.out or "runs/reproduce")
    campaigns = []
    for fig in FIGURES.values():
        try:
            body = figure_body(fig, args)
        except (ValueError, OSError, ValidationError) as err:
            return _refuse(f"{fig.name}: {error_text(err)}")
        campaigns.append(campaign(fig, body, args.profile, parent / out_name(fig, args), None))
    return reproduce_slurm(campaigns, args, parent.resolve() / ".slurm")


def reproduce_local(
    fig: FigureDef, body: dict[str, Any], profile: str, out: Path, args: argparse.Namespace
) -> int:
    """The figure's runs as run groups in this process (or, with --report-only, none),
    then the report from the runs' folders."""
    from cli.local import expand_body, run_groups

    _, _, runs = expand_body(body)
    runs_dir = Path(args.runs) if args.runs else out / "runs"
    if args.group_runs:  # one group of the figure (a Slurm task's): no page
        chosen = [r for r in runs if r.name in set(args.group_runs)]
        unknown = sorted(set(args.group_runs) - {r.name for r in chosen})
        if unknown:
            return _refuse(f"--group-runs: no run {', '.join(unknown)} in this figure's runs")
        return run_groups(chosen, runs_dir, len(chosen), args.quiet, jobs=1)
    code = 0
    if not args.report_only:
        t0 = time.monotonic()
        code = run_groups(runs, runs_dir, args.group_size, args.quiet, jobs=args.jobs)
        print(f"trained in {time.monotonic() - t0:,.0f} s", file=sys.stderr)
    elif not runs_dir.exists():
        return _refuse(f"--report-only: no runs stored in {runs_dir}")
    else:
        from cli.runs_folder import unwritable

        if why := unwritable(out):  # (before the runs are read: no traceback midway)
            return _refuse(f"--out {out}: cannot write the page there ({why})")
    page = write_page(fig, body, profile, out, runs_dir, not args.report_only, figure_flags(args))
    return code or page


def figure_flags(args: argparse.Namespace) -> list[str]:
    """The flags that select a figure's runs, their configs and their folder (seeds,
    episodes, precision, threads, device, arms, --runs): what a command that resumes
    the same runs must repeat."""
    argv = ["--seeds", *map(str, args.seeds)] if args.seeds else []
    for flag in ("episodes", "precision", "threads", "device"):
        if getattr(args, flag) is not None:
            argv += [f"--{flag}", str(getattr(args, flag))]
    argv += ["--runs", str(args.runs)] if args.runs else []
    return argv + (["--arms", *args.arms] if args.arms else [])


def launcher_error(args: argparse.Namespace) -> str | None:
    """Why the launcher flags do not fit together, or None."""
    if args.launcher == "slurm" and not (args.local or args.report_only or args.status):
        return "--launcher slurm: give --local (the figure's run groups are the Slurm tasks)"
    if args.launcher != "slurm":
        for flag in ("partition", "time", "account", "sbatch_args"):
            if getattr(args, flag):
                return f"--{flag.replace('_', '-')} is for --launcher slurm"
        if args.detach:
            return "--detach is for --launcher slurm"
    if args.group_runs and (not args.local or args.report_only or args.status):
        return "--group-runs trains with --local (not with --report-only or --status)"
    if args.status and args.report_only:  # (--status went first: no page was written)
        return "--status and --report-only: give one (the runs' progress, or their page)"
    return None


def _refuse(msg: str) -> int:
    print(f"macb reproduce: {msg}", file=sys.stderr)
    return 2


def _env_url() -> str | None:
    return settings().api_url
