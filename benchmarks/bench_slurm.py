"""A figure's run groups through Slurm against the same groups with the local launcher:
`macb reproduce FIGURE --local --launcher slurm` vs `macb reproduce FIGURE --local`,
the same flags, alternated A B A B (each round a fresh runs folder), run-steps/s.

Each variant's rate is measured two ways, both over every run of the figure:
* `command`: the runs' env steps over the command's wall time (what a user waits,
  Slurm's submission, scheduling and following included);
* `train`: the sum over runs of env steps over the run's own clock at its last row
  (`wall_s`), i.e. the groups' training rate with their start-up left out.
The ratio slurm / local is taken within each round, then the median over rounds. For
the Slurm variant it also says whether its tasks ran at the same time (every task had
started before the first one's runs were done). The CPU is named in the table and the
JSON.

Slurm: the one the environment reaches (`sinfo` answers, e.g. with SLURM_CONF set);
otherwise, as root, a one-node Slurm of its own started from a temp folder as `make
test-slurm` does (tests/slurm_node.py; `--setup` lets it install Debian's munge and
slurm-wlm first), stopped at the end.

    .venv/bin/python benchmarks/bench_slurm.py [--figure fig8] [--episodes 200]
        [--arms 'sparse*'] [--rounds 2] [--setup]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from _harness import add_out, bench_parser, command, macb_argv, progress, write_result
from _procs import ROOT
from _stats import cpu_model, fmt, median

VARIANTS = ("local", "slurm")  # A, B


@contextlib.contextmanager
def slurm(setup: bool) -> Iterator[dict[str, str]]:
    """The environment that reaches a Slurm: this one's, or a one-node Slurm of ours."""
    if shutil.which("sinfo"):
        got = subprocess.run(["sinfo", "-h"], capture_output=True, text=True, timeout=30)
        if got.returncode == 0 and got.stdout.strip():
            progress(f"using the Slurm this environment reaches ({got.stdout.split()[0]} ...)")
            yield dict(os.environ)
            return
    from tests import slurm_node

    with tempfile.TemporaryDirectory(prefix="bench-slurm-node-") as folder:
        try:
            node = slurm_node.start(Path(folder), may_set_up=setup)
        except slurm_node.Unavailable as err:
            raise SystemExit(f"no Slurm to measure on: {err}") from err
        progress(f"a one-node Slurm of ours is up ({node.env['SLURM_CONF']})")
        try:
            yield node.env
        finally:
            node.stop()


def runs_of(out: Path) -> list[Path]:
    return sorted(p for p in (out / "runs").iterdir() if p.is_dir() and not p.name.startswith("."))


def last_row(run: Path) -> dict[str, Any]:
    lines = (run / "metrics.jsonl").read_text().splitlines()
    return json.loads(lines[-1]) if lines else {}


def task_spans(out: Path) -> list[tuple[float, float]]:
    """Each Slurm task's (start, end): its log's first start line, and the newest file
    written in its runs' folders."""
    slurm_dir = out / "runs" / ".slurm"
    (sub,) = json.loads((slurm_dir / "jobs.json").read_text())["submissions"]
    spans = []
    for t in sub["tasks"]:
        log = (slurm_dir / f"{sub['job']}_{t['index']}.log").read_text()
        stamp = re.search(r" at (\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ)", log)
        assert stamp, log[:500]
        start = datetime.strptime(stamp[1], "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=UTC).timestamp()
        ends = [f.stat().st_mtime for r in t["runs"] for f in (out / "runs" / r).rglob("*")]
        spans.append((start, max(ends)))
    return spans


def one(variant: str, args: argparse.Namespace, env: dict[str, str], work: Path) -> dict:
    out = work / variant
    argv = ["reproduce", args.figure, "--local", "--episodes", str(args.episodes), "--quiet"]
    argv += ["--arms", *args.arms] if args.arms else []
    argv += ["--out", str(out)] + (["--launcher", "slurm"] if variant == "slurm" else [])
    t0 = time.monotonic()
    got = subprocess.run(macb_argv(*argv), cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.monotonic() - t0
    if got.returncode:
        raise SystemExit(f"macb {' '.join(argv)} failed ({got.returncode}):\n{got.stderr[-3000:]}")
    rows = [last_row(r) for r in runs_of(out)]
    steps = sum(int(r["env_steps"]) for r in rows)
    result = {
        "command": steps / wall,
        "train": sum(int(r["env_steps"]) / float(r["wall_s"]) for r in rows),
        "wall_s": wall,
        "runs": len(rows),
        "env_steps": steps,
    }
    if variant == "slurm":
        spans = task_spans(out)
        result["tasks"] = len(spans)
        result["concurrent"] = max(s for s, _ in spans) < min(e for _, e in spans)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "slurm.json")
    parser.add_argument("--figure", default="fig8")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--arms", nargs="*", default=["sparse*"], help="as macb reproduce's")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of A B (local, slurm)")
    parser.add_argument("--setup", action="store_true", help="may install munge and slurm-wlm")
    add_out(parser, "slurm.json")
    args = parser.parse_args(argv)
    load = os.getloadavg()
    got: dict[str, list[dict]] = {v: [] for v in VARIANTS}
    with slurm(args.setup) as env, tempfile.TemporaryDirectory(prefix="bench-slurm-") as tmp:
        for r in range(args.rounds):
            for variant in VARIANTS:  # A B A B: the acceptance's order
                work = Path(tmp) / f"round{r}"
                work.mkdir(exist_ok=True)
                progress(f"round {r + 1}/{args.rounds}: {variant} (load {os.getloadavg()[0]:.2f})")
                got[variant].append(one(variant, args, env, work))
                shutil.rmtree(work / variant, ignore_errors=True)
    ratios = {
        how: [s[how] / a[how] for a, s in zip(got["local"], got["slurm"], strict=True)]
        for how in ("command", "train")
    }
    result = {
        "command": command(__file__, argv),
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "rounds": got,
        "ratio": {how: median(v) for how, v in ratios.items()},
        "ratios": ratios,
    }
    what = f"{args.figure}, {args.episodes} episodes, arms {' '.join(args.arms)}"
    print(f"\nCPU: {result['cpu']} ({result['cores']} cores); {what}, {args.rounds} round(s) A B")
    print("\n| run-steps/s (median) | local | slurm | slurm / local (median of rounds) |")
    print("|---|---|---|---|")
    for how in ("command", "train"):
        cells = [fmt(median(x[how] for x in got[v])) for v in VARIANTS]
        print(f"| {how} | {cells[0]} | {cells[1]} | {fmt(result['ratio'][how], '.3f')}x |")
    tasks = [(x["tasks"], x["concurrent"]) for x in got["slurm"]]
    print(f"\nSlurm tasks per round (count, all running at once): {tasks}")
    write_result(args.out, result, load)


if __name__ == "__main__":
    sys.exit(main())
