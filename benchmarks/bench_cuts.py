"""What cuts cost a one-process run: bytes and seconds per cut, and the share of wall time.

A cut (shared/persist/cuts.py) appends the replay rows collected since the last one and writes
the learner, count tables and RNG states atomically with fsync; `macb train` writes one
at the first evaluation point after every 60 s (`--cut-every`). This runs the trainer at
thesis settings on speaker_listener (Cen-MADDPG + Cen-MACB, k 512, 400-300, batch 100)
twice per round, alternating: `rare` (one cut, at the end) and `often` (a cut at every
evaluation point, far more often than the default), and reports each cut's time and
bytes, the wall-time ratio often/rare per round (median), and the share of wall time
cuts take at the default interval: cut seconds / (60 s + cut seconds).

    .venv/bin/python benchmarks/bench_cuts.py [--quick] [--rounds 3] [--episodes 100]
"""

# ruff: noqa: E402
from __future__ import annotations

from _procs import pin_threads

pin_threads()  # as every service runs; before numpy is imported

import math
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _harness import (
    THESIS_ARM,
    add_out,
    begin_run,
    bench_parser,
    command,
    progress,
    write_result,
)
from _stats import fmt, ratio_median

from cli.trainer import DEFAULT_CUT_EVERY_S, GroupRun
from shared.config import make_config

THESIS = {**THESIS_ARM, "learner_lanes": 1}


def one_run(cfg, out: Path, cut_every_s: float) -> dict:
    run = GroupRun([cfg], [out], cut_every_s)
    t0 = time.perf_counter()
    run.go(False, None)
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "env_steps": run.members[0].env_steps, "cuts": run.cut_log}


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__, "cuts.json")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--eval-every", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="tiny networks, 2 rounds")
    add_out(parser, "cuts.json")
    args = parser.parse_args(argv)
    extra = {"hidden": [32, 32], "batch_size": 16, "k": 64} if args.quick else {}
    rounds = 2 if args.quick else args.rounds
    cfg = make_config({**THESIS, **extra, "episodes": args.episodes, "eval_every": args.eval_every})
    work = Path(tempfile.mkdtemp(prefix="bench-cuts-"))
    load = begin_run(work / "r", "cuts")
    results: dict[str, list[dict]] = {"rare": [], "often": []}
    try:
        for r in range(rounds):
            order = ("rare", "often") if r % 2 == 0 else ("often", "rare")
            for variant in order:
                out = work / f"{variant}-{r}"
                every = math.inf if variant == "rare" else 0.0
                results[variant].append(one_run(cfg, out, every))
                progress(
                    f"round {r + 1}/{rounds} {variant}: {results[variant][-1]['wall_s']:.1f} s"
                )
                shutil.rmtree(out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    cuts = [c for run in results["often"] for c in run["cuts"][:-1]]  # the final one aside
    cut_s = statistics.median(c[1] for c in cuts)
    per_cut_replay = int(statistics.median(c[2] for c in cuts))
    per_cut_file = int(statistics.median(c[3] for c in cuts))
    ratio = ratio_median(
        [o["wall_s"] for o in results["often"]], [r["wall_s"] for r in results["rare"]]
    )
    steps_per_s = statistics.median(r["env_steps"] / r["wall_s"] for r in results["rare"])
    share = cut_s / (DEFAULT_CUT_EVERY_S + cut_s)
    summary = {
        "cut_s_median": cut_s,
        "cut_s_max": max(c[1] for c in cuts),
        "replay_bytes_per_cut": per_cut_replay,
        "cut_file_bytes": per_cut_file,
        "cuts_per_often_run": len(results["often"][0]["cuts"]),
        "wall_ratio_often_over_rare": ratio,
        "steps_per_s_rare": steps_per_s,
        "share_at_default_interval": share,
        "target_share_le": 0.03,
        "met": share <= 0.03,
    }
    print(
        "| cut (median) | cut (max) | replay bytes/cut | cut file | often/rare wall | share @60 s |"
    )
    print("|---|---|---|---|---|---|")
    print(
        f"| {cut_s * 1e3:.1f} ms | {summary['cut_s_max'] * 1e3:.1f} ms | {per_cut_replay:,} "
        f"| {per_cut_file:,} B | {fmt(ratio, '.3f')} | {100 * share:.2f}% |"
    )
    write_result(
        args.out,
        {
            "command": command(__file__, argv),
            "config": cfg.model_dump(mode="json"),
            "rounds": results,
            "summary": summary,
        },
        load,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
