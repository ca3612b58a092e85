"""Runs at once on one machine: total env steps/s of `macb up --slots S` running S seeds
of one arm, against one run alone, and what that makes of figure 8's headline pair.

Issue 13's target: two runs at once on the 2-core machine give >= 1.3x one run alone in
total env steps/s. Each variant is a whole `macb up --slots S --run CONFIG --seeds 0 ..
S-1 --episodes E` (router, counter, S learners and evaluators, S actors, API), in
rounds whose order rotates; `alone` is `--slots 1` with one seed. A run's rate is its
steady rate from its own metric rows (env steps from a third of the run to its end over
its learner's clock, as bench_cluster_bf16.py takes it); a variant's total is the sum
over its runs, which overlap for all but their first and last seconds; the command's
rate (all env steps over the whole command, startup included) is shown beside.

The projection: figure 8's headline pair (its sparse Cen-MACB and sparse Cen-MADDPG
arms, 3 seeds each, configs/fig8's 4e4 episodes of 20 steps: 4.8e6 env steps) at
the measured total rate, the arms run S at a time.

    .venv/bin/python benchmarks/bench_slots.py [--rounds 3] [--episodes 300]
        [--slots 2 [3 ...]] [--precision bf16] [--config configs/fig8/sparse-cen-macb.yaml]

Several counts (`--slots 2 3`) are variants of the same rounds, each against the same
runs alone.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from _harness import (
    FIG8_PAIR_RUN_STEPS,
    add_out,
    bench_parser,
    command,
    macb_argv,
    metric_rows,
    progress,
    ran_precision,
    write_result,
)
from _procs import ROOT
from _stats import fmt, median, ratio_median, rotating_rounds
from bench_cluster_bf16 import steady_rate

from cli.supervisor import free_port


def run_variant(slots: int, args: Any, work: Path) -> dict[str, Any]:
    out, data = work / f"s{slots}-out", work / f"s{slots}-data"
    seeds = [str(s) for s in range(slots)]
    argv = macb_argv(
        "up", "--slots", str(slots), "--run", str(args.config), "--seeds", *seeds,
        "--episodes", str(args.episodes), "--precision", args.precision,
        "--out", str(out), "--data-dir", str(data),
        "--endpoint", f"tcp/127.0.0.1:{free_port()}", "--api-port", str(free_port()),
        "--quiet", "--quiet-services",
    )  # fmt: skip
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, check=False)
    total_s = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"--slots {slots} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    run_dirs = sorted(d for d in out.iterdir() if (d / "metrics.csv").is_file())
    if slots == 1 and not run_dirs:
        run_dirs = [out]  # one run: its rows are out/metrics.csv itself
    rates, steps, ran = [], 0.0, []
    for d in run_dirs:
        rows = metric_rows(d)
        rates.append(steady_rate(rows)[0])
        steps += float(rows[-1]["env_steps"])
        ran.append(ran_precision(d))
    if len(rates) != slots:
        raise SystemExit(f"--slots {slots}: {len(rates)} runs' metrics in {out}, not {slots}")
    shutil.rmtree(data, ignore_errors=True)
    shutil.rmtree(out, ignore_errors=True)
    return {"slots": slots, "per_run": rates, "total": sum(rates), "ran": ran,
            "command_rate": steps / total_s, "command_s": total_s, "load": load}  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "slots.json")
    parser.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    parser.add_argument("--episodes", type=int, default=300, help="per run (default 300)")
    parser.add_argument(
        "--slots", type=int, nargs="+", default=[2],
        help="runs at once, one or more counts, each its own variant (default 2)",
    )  # fmt: skip
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="bf16")
    parser.add_argument(
        "--config", type=Path, default=ROOT / "configs" / "fig8" / "sparse-cen-macb.yaml",
        help="the arm (default configs/fig8/sparse-cen-macb.yaml)",
    )  # fmt: skip
    add_out(parser, "slots.json")
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.episodes < 6 or min(args.slots) < 2:
        parser.error("--rounds must be >= 1, --episodes >= 6 and every --slots >= 2")
    counts = sorted(set(args.slots))
    load = os.getloadavg()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="macb-slots-") as tmp:
        for r, slots in rotating_rounds(args.rounds, [1, *counts]):
            load_now = os.getloadavg()[0]
            progress(f"round {r + 1}/{args.rounds}: --slots {slots} (load {load_now:.2f})")
            run = run_variant(slots, args, Path(tmp))
            progress(f"  total {run['total']:.1f} env steps/s (runs "
                     f"{', '.join(f'{x:.1f}' for x in run['per_run'])}), command "
                     f"{run['command_rate']:.1f} over {run['command_s']:.0f} s")  # fmt: skip
            runs.append({"round": r, **run})
    summary = summarise(runs, counts)
    arm = args.config.relative_to(ROOT) if args.config.is_relative_to(ROOT) else args.config
    ran = sorted({str(p) for x in runs for p in x["ran"]})
    note = (
        " (**ran fp32**: no native bf16 here)" if args.precision != "fp32" and "fp32" in ran else ""
    )
    print(f"\n{arm}, {args.precision}{note}, {args.episodes} episodes per run\n")
    print("| variant | total env steps/s (median) | per round | command rate | / alone "
          "| figure 8's pair |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for slots in [1, *counts]:
        group = [x for x in runs if x["slots"] == slots]
        name = "1 run alone" if slots == 1 else f"{slots} runs at once"
        s = summary.get(slots, {})
        ratio = f"**{s['ratio']:.2f}x** (command {s['command_ratio']:.2f}x)" if s else "-"
        print(f"| {name} | {fmt(median(x['total'] for x in group))} "
              f"| {', '.join(fmt(x['total']) for x in group)} "
              f"| {fmt(median(x['command_rate'] for x in group))} | {ratio} "
              f"| {fmt(hours(group), '.1f')} h |")  # fmt: skip
    print(
        "\n- / alone: median of per-round ratios of total steady env steps/s (the command "
        "rate's ratio beside it)\n- figure 8's headline pair: 2.6e6 env steps at the "
        "variant's median total"
    )
    write_result(
        args.out,
        {"command": command(__file__, argv), "config": str(args.config), "slots": counts,
         "precision": args.precision, "episodes": args.episodes, "runs": runs,
         "summary": {str(k): v for k, v in summary.items()}},
        load,
    )  # fmt: skip


def hours(group: list[dict[str, Any]]) -> float | None:
    """Figure 8's headline pair, in hours, at the median total rate of these runs."""
    total = median(x["total"] for x in group)
    return FIG8_PAIR_RUN_STEPS / total / 3600 if total else None


def summarise(runs: list[dict[str, Any]], counts: list[int]) -> dict[int, dict[str, Any]]:
    """Per slot count: its ratio to one run alone (median of the rounds' ratios), by
    steady total and by command rate, and figure 8's pair in hours at its rate."""
    alone = [x for x in runs if x["slots"] == 1]
    out: dict[int, dict[str, Any]] = {}
    for slots in counts:
        many = [x for x in runs if x["slots"] == slots]
        out[slots] = {
            "ratio": ratio_median([x["total"] for x in many], [x["total"] for x in alone]),
            "command_ratio": ratio_median(
                [x["command_rate"] for x in many], [x["command_rate"] for x in alone]
            ),
            "fig8_pair_hours": hours(many),
        }
    return out


if __name__ == "__main__":
    main()
