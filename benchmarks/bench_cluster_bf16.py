"""The cluster in bf16 against the cluster of an earlier commit: env steps/s of `macb up`.

The workload is issue 13's: speaker_listener, Cen-MADDPG + Cen-MACB (k 512, beta 0.8),
batch 100, hidden 400-300, an evaluation point after every episode, one actor. Three
variants, each a whole `macb up --run CONFIG --out DIR` (router, counter, learner,
evaluator, actor, API as processes, as a user runs it), in rounds whose order rotates:

* `base`: the baseline commit (default 968ebf2, the cluster before bf16), checked out
  in a git worktree and run from it with this venv (its own code first on PYTHONPATH);
* `fp32`: this tree, `precision: fp32` (the default);
* `bf16`: this tree, `precision: bf16`;
* `bf16-unfused`: the same with `MACB_FUSED=0`: the learner's master-weight work in
  torch's ops instead of the fused kernel (shared/core/learners/fused.py);
* `fp32-1t`, `bf16-1t`: `fp32`, `bf16` with `learner_lanes: 1`, the update on one
  thread always instead of the tuner's pick (shared/core/learners/tuning.py), which leaves
  the other core to the evaluator, actor, counter and router.

A run's throughput is its steady rate from its own metric rows: env steps between the
first row past a third of the run and the last, over the learner's wall clock between
them (the learner's `wall_s`); also the overall rate of the last row and the whole
command's time. Ratios are taken within a round; medians over rounds.

    .venv/bin/python benchmarks/bench_cluster_bf16.py [--rounds 5] [--episodes 300]
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _harness import (
    THESIS_ARM,
    add_out,
    bench_parser,
    command,
    metric_rows,
    progress,
    ran_precision,
    write_result,
)
from _procs import ROOT
from _stats import fmt, median, ratio_median, rotating_rounds

from cli.supervisor import free_port

VARIANTS = ("base", "fp32", "bf16", "bf16-unfused", "fp32-1t", "bf16-1t")


def steady_rate(rows: list[dict[str, str]]) -> tuple[float, float]:
    """(steady env steps/s from a third of the run to its end, overall env steps/s)."""
    steps = [float(r["env_steps"]) for r in rows]
    wall = [float(r["wall_s"]) for r in rows]
    i = next(j for j, s in enumerate(steps) if s >= steps[-1] / 3)
    if i >= len(rows) - 1 or wall[-1] <= wall[i]:
        raise ValueError("too few metric rows for a steady rate: run more episodes")
    return (steps[-1] - steps[i]) / (wall[-1] - wall[i]), steps[-1] / wall[-1]


def write_config(path: Path, episodes: int, precision: str | None, lanes: str | None) -> None:
    lines = [f"{k}: {v}" for k, v in THESIS_ARM.items()]
    lines += [f"episodes: {episodes}", "eval_every: 1", "seed: 0"]
    if precision is not None:  # the baseline's schema may not know the key
        lines.append(f"precision: {precision}")
    if lanes is not None:
        lines.append(f"learner_lanes: {lanes}")
    path.write_text("\n".join(lines) + "\n")


def variant_keys(variant: str) -> tuple[str | None, str | None]:
    """(precision, learner_lanes) a variant's config sets; None: the key is left out
    (the baseline's schema may not know it)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; known: {list(VARIANTS)}")
    if variant == "base":
        return None, None
    return variant.split("-")[0], "1" if variant.endswith("-1t") else None


def run_variant(variant: str, base_tree: Path, work: Path, episodes: int) -> dict[str, Any]:
    tree = base_tree if variant == "base" else ROOT
    cli = "shared.cli" if (tree / "shared" / "cli.py").exists() else "cli"
    cfg = work / f"{variant}.yaml"
    write_config(cfg, episodes, *variant_keys(variant))
    out, data = work / f"{variant}-out", work / f"{variant}-data"
    argv = [sys.executable, "-m", cli, "up", "--run", str(cfg), "--out", str(out)]
    argv += ["--data-dir", str(data), "--endpoint", f"tcp/127.0.0.1:{free_port()}"]
    argv += ["--api-port", str(free_port()), "--quiet", "--quiet-services"]
    env = {**os.environ, "PYTHONPATH": str(tree)}
    if variant == "bf16-unfused":
        env["MACB_FUSED"] = "0"
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(argv, cwd=tree, env=env, capture_output=True, text=True, check=False)
    total = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{variant} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    rows = metric_rows(out)
    steady, overall = steady_rate(rows)
    shutil.rmtree(data, ignore_errors=True)
    return {"variant": variant, "steady": steady, "overall": overall, "command_s": total,
            "rows": len(rows), "load": load, "ran": ran_precision(out)}  # fmt: skip


def fell_back_to_fp32(run: dict[str, Any]) -> bool:
    """A bf16 variant's run whose learner ran fp32 (no native bf16 on this CPU)."""
    return variant_keys(run["variant"])[0] == "bf16" and run["ran"] == "fp32"


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "cluster-bf16.json")
    parser.add_argument("--rounds", type=int, default=5, help="rounds (default 5)")
    parser.add_argument("--episodes", type=int, default=300, help="per run (default 300)")
    parser.add_argument("--baseline", default="968ebf2", help="commit of `base` (968ebf2)")
    parser.add_argument(
        "--variants", default=",".join(VARIANTS), help=f"subset of {','.join(VARIANTS)}"
    )
    add_out(parser, "cluster-bf16.json")
    args = parser.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    if bad := [v for v in variants if v not in VARIANTS]:
        parser.error(f"unknown variant(s) {bad}; known: {list(VARIANTS)}")
    if args.rounds < 1 or args.episodes < 6:
        parser.error("--rounds must be >= 1 and --episodes >= 6")
    load = os.getloadavg()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="macb-cluster-bf16-") as tmp:
        base_tree = Path(tmp) / "base"
        if "base" in variants:
            subprocess.run(
                ["git", "worktree", "add", "--detach", "-q", str(base_tree), args.baseline],
                cwd=ROOT, check=True,
            )  # fmt: skip
        try:
            for r, variant in rotating_rounds(args.rounds, variants):
                work = Path(tmp) / f"r{r}"
                work.mkdir(exist_ok=True)
                progress(f"round {r + 1}/{args.rounds}: {variant} (load {os.getloadavg()[0]:.2f})")
                run = run_variant(variant, base_tree, work, args.episodes)
                progress(f"  steady {run['steady']:.1f} env steps/s, overall "
                         f"{run['overall']:.1f}, command {run['command_s']:.0f} s")  # fmt: skip
                runs.append({"round": r, **run})
        finally:
            if "base" in variants:
                subprocess.run(
                    ["git", "worktree", "remove", "--force", str(base_tree)], cwd=ROOT,
                    check=False,
                )  # fmt: skip
    by = {v: [x for x in runs if x["variant"] == v] for v in variants}
    lines = ["| variant | ran in | steady env steps/s | overall env steps/s | command s |",
             "|---|---|---|---|---|"]  # fmt: skip
    for v in variants:
        ran = sorted({str(x["ran"] or "-") for x in by[v]})
        lines.append(
            f"| {v} | {', '.join(ran)} | {fmt(median(x['steady'] for x in by[v]))} "
            f"| {fmt(median(x['overall'] for x in by[v]))} "
            f"| {fmt(median(x['command_s'] for x in by[v]))} |"
        )
    if fell_back := sorted({x["variant"] for x in runs if fell_back_to_fp32(x)}):
        lines.append(
            f"\n**{', '.join(fell_back)} ran fp32**: this CPU has no native bf16, so their "
            "ratios compare fp32 with fp32 (the runs' provenance.json)."
        )
    ratios = {}
    pairs = [
        ("bf16", "base"), ("fp32", "base"), ("bf16", "fp32"), ("bf16-unfused", "base"),
        ("bf16", "bf16-unfused"), ("bf16-1t", "base"), ("fp32-1t", "base"),
        ("bf16-1t", "bf16"), ("fp32-1t", "fp32"),
    ]  # fmt: skip
    for a, b in pairs:
        if a in by and b in by:
            for what in ("steady", "overall"):
                ratios[f"{a}/{b} {what}"] = ratio_median(
                    [x[what] for x in by[a]], [x[what] for x in by[b]]
                )
    print("\n".join(lines))
    print()
    for name, value in ratios.items():
        print(f"- {name}: **{value:.2f}x** (median of per-round ratios)")
    write_result(
        args.out,
        {
            "command": command(__file__, argv),
            "baseline": args.baseline,
            "runs": runs,
            "ratios": ratios,
        },  # fmt: skip
        load,
    )


if __name__ == "__main__":
    main()
