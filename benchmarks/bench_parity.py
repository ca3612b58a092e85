"""Learning parity of bf16 against fp32: the same runs in both precisions, compared by seed.

Each case is a short run of `macb train` per seed and precision (one torch thread, one
learner lane: bit-reproducible on a machine, so a result can be re-run exactly):

* `simple`: DDPG + Dis-MACB (beta 0.8, k 64) on sparse simple, configs/fig3/beta0.8.yaml:
  the thesis's figure 3 arm, which learns within a few hundred episodes here;
* `speaker_listener`: Cen-MADDPG on dense speaker_listener (configs/fig8/dense.yaml's
  arm): the sparse arms show no success in a short run, the dense return does move.

A run's curve is summed up by its area per point (the mean over its evaluation points)
of the success rate and of the evaluation return; benchmarks/parity.py compares the paired
per-seed differences by two one-sided t-tests (TOST, alpha 0.05): `equivalent` when the
90% interval of the mean difference lies inside the margin: 0.1 of success rate, and
10% of fp32's mean return area for the return. `--null` adds a third run per seed,
fp32 with the per-agent reference learner (the same arithmetic in another order), and
the same comparison of it against fp32: how far two runs of one precision part by
rounding alone, the yardstick for bf16's differences. Runs go `--jobs` at a time
(learning results do not depend on load; the time ratio per pair, printed, does).

    .venv/bin/python benchmarks/bench_parity.py [--quick]
"""

from __future__ import annotations

import os
import statistics
import subprocess
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from _harness import (
    add_out,
    bench_parser,
    command,
    macb_argv,
    metric_rows,
    progress,
    write_result,
)
from _procs import ROOT
from parity import curve_auc, paired_equivalence

CASES: dict[str, dict[str, Any]] = {
    "simple": {
        "argv": ["--config", str(ROOT / "configs/fig3/beta0.8.yaml")],
        "episodes": 400,
        "seeds": 8,
    },
    "speaker_listener": {
        "argv": ["--task", "speaker_listener", "--algo", "cen-maddpg", "--explore", "none"]
        + ["--reward", "dense"],
        "episodes": 500,
        "seeds": 6,
    },
}
# The variants a run can be: the two precisions, and with --null a second fp32 (the
# per-agent reference learner: the same math summed in another order), whose pairing
# with fp32 shows how far two runs part by rounding alone, whatever the precision.
VARIANTS = {
    "fp32": ["--precision", "fp32"],
    "bf16": ["--precision", "bf16"],
    "fp32-ref": ["--precision", "fp32", "--learner-impl", "reference"],
}
SUCCESS_MARGIN = 0.1  # of success rate (absolute)
RETURN_MARGIN = 0.1  # of fp32's mean return area (relative)


def run_one(work: Path, case: str, seed: int, variant: str, episodes: int) -> dict[str, Any]:
    """One `macb train` run; its metric rows and wall time."""
    out = work / f"{case}-s{seed}-{variant}"
    argv = macb_argv("train", *CASES[case]["argv"], "--out", str(out), "--quiet")
    argv += ["--episodes", str(episodes), "--eval-every", "25", "--seed", str(seed)]
    argv += [*VARIANTS[variant], "--threads", "1", "--learner-lanes", "1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{case} seed {seed} {variant} failed:\n{proc.stderr[-2000:]}")
    rows = metric_rows(out)
    if variant == "bf16" and "runs fp32" in proc.stderr:
        raise SystemExit(f"no native bf16 here: {proc.stderr.strip().splitlines()[-1]}")
    return {
        "case": case,
        "seed": seed,
        "variant": variant,
        "wall_s": wall,
        "success_auc": curve_auc(rows, "success_rate"),
        "return_auc": curve_auc(rows, "eval_return"),
        "final_success": float(rows[-1]["success_rate"]),
        "curve": [float(r["success_rate"]) for r in rows],
    }


def compare(runs: list[dict[str, Any]], case: str, other: str = "bf16") -> dict[str, Any]:
    """fp32 against `other`, paired by seed, on both metrics."""
    by = {(r["seed"], r["variant"]): r for r in runs if r["case"] == case}
    seeds = sorted({s for s, _ in by})
    a = [by[s, "fp32"] for s in seeds]
    b = [by[s, other] for s in seeds]
    success = paired_equivalence(
        [r["success_auc"] for r in a], [r["success_auc"] for r in b], SUCCESS_MARGIN,
        metric="success_auc",
    )  # fmt: skip
    fp32_return = statistics.mean(r["return_auc"] for r in a)
    ret = paired_equivalence(
        [r["return_auc"] for r in a], [r["return_auc"] for r in b],
        RETURN_MARGIN * abs(fp32_return), metric="return_auc",
    )  # fmt: skip
    time_ratio = statistics.median(y["wall_s"] / x["wall_s"] for x, y in zip(a, b, strict=True))
    return {"case": case, "against": other, "seeds": seeds,
            "tests": [success.as_dict(), ret.as_dict()], "over_fp32_wall": time_ratio}  # fmt: skip


def table(results: list[dict[str, Any]]) -> str:
    lines = [
        "| case | fp32 vs | metric | seeds | fp32 mean | its mean | mean diff | 90% interval "
        "| margin | p (TOST) | p (difference) | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for res in results:
        for t in res["tests"]:
            lines.append(
                f"| {res['case']} | {res['against']} | {t['metric']} | {t['n']} "
                f"| {t['mean_a']:.3f} | {t['mean_b']:.3f} | {t['mean_diff']:+.3f} "
                f"| [{t['ci_low']:+.3f}, {t['ci_high']:+.3f}] | {t['margin']:.3f} "
                f"| {t['p_tost']:.3f} | {t['p_difference']:.3f} | **{t['verdict']}** |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "parity.json")
    parser.add_argument(
        "--quick", action="store_true", help="simple only, 3 seeds, 400 episodes (~2-3 min)"
    )
    parser.add_argument("--cases", default=",".join(CASES), help=f"subset of {','.join(CASES)}")
    parser.add_argument("--seeds", type=int, help="seeds per case (default: 8 simple, 6 s_l)")
    parser.add_argument("--episodes", type=int, help="per run (default: 400 simple, 500 s_l)")
    parser.add_argument("--jobs", type=int, default=2, help="runs at a time (default 2)")
    parser.add_argument(
        "--null", action="store_true",
        help="also fp32 with the reference learner: the spread of two fp32 runs' pairing",
    )  # fmt: skip
    add_out(parser, "parity.json")
    args = parser.parse_args(argv)
    cases = ["simple"] if args.quick else [c.strip() for c in args.cases.split(",") if c]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        parser.error(f"unknown case(s) {unknown}; known: {list(CASES)}")
    if args.jobs < 1:
        parser.error("--jobs must be >= 1")
    load = os.getloadavg()
    jobs = []
    for case in cases:
        seeds = args.seeds or (3 if args.quick else CASES[case]["seeds"])
        episodes = args.episodes or CASES[case]["episodes"]
        for seed in range(seeds):
            variants = ["fp32", "bf16", *(["fp32-ref"] if args.null else [])]
            order = variants if seed % 2 == 0 else variants[::-1]  # A B, B A, ...
            jobs += [(case, seed, v, episodes) for v in order]
    runs: list[dict[str, Any]] = []
    with (
        tempfile.TemporaryDirectory(prefix="macb-parity-") as tmp,
        ThreadPoolExecutor(args.jobs) as pool,
    ):
        futures = [pool.submit(run_one, Path(tmp), *job) for job in jobs]
        for i, fut in enumerate(futures, 1):
            run = fut.result()
            runs.append(run)
            progress(
                f"[{i}/{len(jobs)}] {run['case']} seed {run['seed']} {run['variant']}: "
                f"success area {run['success_auc']:.3f}, return area "
                f"{run['return_auc']:.2f}, {run['wall_s']:.0f} s"
            )
    results = [compare(runs, case) for case in cases]
    if args.null:
        results += [compare(runs, case, "fp32-ref") for case in cases]
    print(table(results))
    for res in results:
        print(f"{res['case']}: {res['against']} / fp32 wall time per pair, median "
              f"{res['over_fp32_wall']:.2f} (runs {args.jobs} at a time)")  # fmt: skip
    write_result(
        args.out,
        {
            "command": command(__file__, argv),
            "results": results,
            "runs": runs,
            "jobs": args.jobs,
            "load_before": load,
        },  # fmt: skip
        load,
    )


if __name__ == "__main__":
    main()
