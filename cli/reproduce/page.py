"""A `--local` campaign's page from its runs' folders: FIGURE.png/.md/.csv.gz and
FIGURE-runs.json, written by `macb reproduce --local` (and --report-only) after training
in this process, and by `--launcher slurm` once every task's runs are complete.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cli.reproduce.defs import FigureDef


def write_runs_record(exp: dict[str, Any], path: Path) -> Path:
    """Every run of a local reproduce: id, arm, seed, status, config, the provenance
    of its latest start (code, machine, libraries, the precision as run) and the CPU of
    each of its starts (`start_cpus`: which CPUs rounded its rows, for `macb results
    --compare`) and the code of each (`start_codes`)."""
    import json

    keep = ("id", "arm", "seed", "status", "config")
    runs = [
        {
            **{k: r[k] for k in keep},
            "provenance": (r.get("live") or {}).get("provenance"),
            "start_cpus": r.get("start_cpus"),
            "start_codes": r.get("start_codes"),
        }
        for r in exp["runs"]
    ]
    record = {"experiment": exp["name"], "wall_s": exp.get("wall_s"), "runs": runs}
    path.write_text(json.dumps(record, indent=1) + "\n")
    return path


def write_page(
    fig: FigureDef,
    body: dict[str, Any],
    profile: str,
    out: Path,
    runs_dir: Path,
    trained: bool,
    flags: Sequence[str] = (),
) -> int:
    """The page (FIGURE.png/.md/.csv.gz, FIGURE-runs.json) from the runs in `runs_dir`:
    0 when every run completed, 1 when some did not, 2 when a run's rows cannot be read,
    its folder holds another config's run or no run has a folder (named; nothing
    written: an empty page, or another config's rows, would stand as this figure's).
    `trained`: this command trained them (the page names it), else it names the --local
    command that would, with `flags`, the runs' selection and folder (--arms, --seeds,
    --episodes, --runs, ...: without them that command would train other runs)."""
    import shlex

    from cli.local import (
        TRAINED_WITH,
        MetricsError,
        config_conflicts,
        expand_body,
        foreign_runs,
        local_experiment,
        local_points,
    )
    from cli.reproduce.analysis import analyse, claim_verdicts, columns
    from cli.reproduce.render import write_report

    name, seeds, runs = expand_body(body)
    if not any((runs_dir / r.name).is_dir() for r in runs):
        why = foreign_runs(runs, runs_dir) or (
            f"none of the {len(runs)} run(s) selected has a folder in {runs_dir} (give the "
            "runs folder, OUT/runs, and the flags they were trained with: --seeds, --arms, "
            "...)"
        )
        print(f"macb reproduce: {why}: no page written", file=sys.stderr)
        return 2
    if conflicts := config_conflicts(runs, runs_dir):
        for line in conflicts:
            print(f"macb reproduce: {line}", file=sys.stderr)
        print(f"macb reproduce: no page written: {TRAINED_WITH} or another --runs", file=sys.stderr)
        return 2
    try:
        exp = local_experiment(name, seeds, runs, runs_dir)
        points = {k: columns(v) for k, v in local_points(runs, runs_dir).items()}
    except MetricsError as err:
        print(f"macb reproduce: {err}", file=sys.stderr)
        return 2
    analysis = analyse(fig, exp, points)
    command = shlex.join(["macb", *sys.argv[1:]]) if trained else ""
    rebuild = ["macb", "reproduce", fig.name, "--local", "--profile", profile, *flags]
    command = command or shlex.join(rebuild)
    paths = write_report(analysis, points, profile, out, command)
    paths.append(write_runs_record(exp, out / f"{fig.name}-runs.json"))
    verdicts = [v for *_, v in claim_verdicts(analysis)]
    tally = ", ".join(f"{verdicts.count(v)} {v}" for v in dict.fromkeys(verdicts))
    counts = ", ".join(f"{v} {k}" for k, v in exp["counts"].items())
    print(
        f"{fig.name}: {counts}; claims: {tally}; wrote " + ", ".join(str(p) for p in paths),
        file=sys.stderr,
    )
    return 0 if exp["status"] == "completed" else 1
