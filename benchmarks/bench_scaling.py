"""How the costs grow: learner update vs agents, counting vs k, cluster vs actors.

1. Learner update time for spread with N = 2, 3, 4 agents (Cen-MADDPG, batch 100,
   hidden 400-300, 1 torch thread), reference and batched learner, through
   benchmarks/bench_learner.py's own functions. All six updates are timed in the same
   rounds (rotating order); the baseline is N = 2 of the same learner, and ratios are
   medians of per-round ratios.
2. Counting cost vs k = 64, 128, 256, 512 on speaker_listener's 19-dim s||a for a
   100-row batch, in-process: SimHash keys, table increment, table look-up (counts),
   on a table holding 20,000 keys. Timed in child processes with one BLAS thread (as
   every service runs) and with the BLAS default (as `macb train` runs from a plain
   shell), alternated in rounds; the baseline is k = 64 with one thread.
3. Cluster throughput with 1 vs 2 actors: short `macb up --run` runs (evaluation only at
   the end), steady-state updates/s from the learner's stats, as in bench_e2e.py; the
   baseline is 1 actor in the same round.

    .venv/bin/python benchmarks/bench_scaling.py [--quick] [--skip learner,counting,cluster]

prints markdown tables and writes benchmarks/results/scaling.json.
"""

# Imports below pin_threads(), which must set the thread variables before numpy loads:
# ruff: noqa: E402
from __future__ import annotations

import os
import sys

from _procs import ROOT, pin_threads, thread_env

# This process times learner updates with one BLAS thread like the services; the
# counting children get their BLAS settings from the parent, untouched here. Set
# before numpy is imported.
if "--_counting" not in sys.argv:
    pin_threads()

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

from _harness import add_out, begin_run, bench_parser, command, exploration, progress, write_result
from _stats import fmt, measure, median, ratio_median, rotating_rounds

KS = (64, 128, 256, 512)
COUNT_ROWS = 100
TABLE_KEYS = 20_000


# ------------------------------------------------------------------ 1. learner vs N
def learner_scaling(repeats: int, budget_s: float) -> dict:
    import torch
    from bench_learner import BATCH, HIDDEN, learner_pair, spread

    torch.set_num_threads(1)
    fns = {}
    for n in (2, 3, 4):
        ref, fast, b = learner_pair(spread(n), "cen-maddpg")
        fns[f"ref N={n}"] = lambda ref=ref, b=b: ref.update(*b)
        fns[f"batched N={n}"] = lambda fast=fast, b=b: fast.update(*b)
    progress("learner: spread N=2,3,4 ...")
    samples = measure(fns, repeats, budget_s)
    rows = []
    for impl in ("ref", "batched"):
        base = samples[f"{impl} N=2"]
        for n in (2, 3, 4):
            s = samples[f"{impl} N={n}"]
            rows.append(
                {
                    "learner": impl,
                    "agents": n,
                    "ms_per_update": 1e3 * median(s),
                    "updates_per_s": 1 / median(s),
                    "time_over_n2": ratio_median(s, base),
                }
            )
    return {
        "batch": BATCH,
        "hidden": list(HIDDEN),
        "repeats": repeats,
        "rows": rows,
        "samples_s": samples,
    }


# ------------------------------------------------------------------ 2. counting vs k
def counting_child(budget_s: float) -> dict:
    """In a child process: per-batch seconds of keys / increment / counts for each k."""
    import numpy as np

    rng = np.random.default_rng(0)
    return {k: count_costs(k, budget_s, rng) for k in KS}


def count_costs(k: int, budget_s: float, rng) -> dict:
    import numpy as np

    config = {"task": "speaker_listener", "algo": "cen-maddpg", "explore": "cen-macb", "k": k}
    _, spec, ex = exploration(config)
    n_batches = TABLE_KEYS // COUNT_ROWS
    obs = rng.uniform(-1, 1, (n_batches, COUNT_ROWS, spec.joint_obs_dim)).astype(np.float32)
    act = rng.uniform(-1, 1, (n_batches, COUNT_ROWS, spec.joint_act_dim)).astype(np.float32)
    keys = [ex.keys(obs[i], act[i])[0] for i in range(n_batches)]
    table, hasher = ex.tables[0], ex.hashers[0]
    for kk in keys:  # the table holds TABLE_KEYS keys; increments below add no keys
        table.increment(kk)
    vec = [np.concatenate([obs[i], act[i]], axis=1) for i in range(n_batches)]

    cpu = {}

    def timed(fn, name: str = "") -> float:
        for i in range(3):
            fn(i)
        calls, t0, c0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < budget_s:
            fn(calls % n_batches)
            calls += 1
        wall = time.perf_counter() - t0
        cpu[name] = (time.process_time() - c0) / wall  # > 1: other threads burn CPU too
        return wall / calls

    # The trainer's cadence: one 100-row hash per update, i.e. every ~8 ms, the process
    # otherwise busy in torch (here: asleep, so any CPU it burns meanwhile is BLAS's).
    paced, c0, t0 = [], time.process_time(), time.perf_counter()
    for i in range(max(20, int(budget_s / 0.008))):
        time.sleep(0.008)
        t = time.perf_counter()
        hasher.keys(vec[i % n_batches])
        paced.append(time.perf_counter() - t)
    paced_cores = (time.process_time() - c0) / (time.perf_counter() - t0)
    return {
        "key_bytes": table.key_bytes,
        "paced_keys_p50_s": float(np.percentile(paced, 50)),
        "paced_keys_p99_s": float(np.percentile(paced, 99)),
        "paced_cores_used": paced_cores,
        "keys_s": timed(lambda i: hasher.keys(vec[i]), "keys"),
        "keys_cpu_over_wall": cpu["keys"],
        "increment_s": timed(lambda i: table.increment(keys[i])),
        "counts_s": timed(lambda i: table.counts(keys[i])),
        "bonus_s": timed(lambda i: ex.bonus(obs[i], act[i])),
        "memory_bytes_per_key": table.memory_bytes() / len(table),
    }


def counting_scaling(rounds: int, budget_s: float, work: Path) -> dict:
    runs = []
    settings = ["1", "default"]
    for r, blas in rotating_rounds(rounds, settings):
        progress(f"counting: round {r + 1}/{rounds}, BLAS threads {blas} ...")
        env = thread_env(blas == "1")
        result = work / f"counting-{r}-{blas}.json"
        subprocess.run(
            [
                sys.executable,
                str(Path(__file__).resolve()),
                "--_counting",
                "--budget",
                str(budget_s),
                "--result",
                str(result),
            ],
            cwd=ROOT,
            env=env,
            check=True,
            timeout=600,
        )
        runs.append(
            {
                "round": r,
                "blas": blas,
                "load": os.getloadavg(),
                "k": json.loads(result.read_text()),
            }
        )
    rows = []
    for blas in settings:
        for k in KS:
            rs = [x for x in runs if x["blas"] == blas]
            per = [x["k"][str(k)] for x in rs]
            base = [
                next(y for y in runs if y["round"] == x["round"] and y["blas"] == "1")["k"]["64"]
                for x in rs
            ]
            total = [p["keys_s"] + p["increment_s"] + p["counts_s"] for p in per]
            base_total = [b["keys_s"] + b["increment_s"] + b["counts_s"] for b in base]
            rows.append(
                {
                    "blas": blas,
                    "k": k,
                    "key_bytes": per[0]["key_bytes"],
                    "keys_us": 1e6 * median([p["keys_s"] for p in per]),
                    "keys_cpu_over_wall": median([p["keys_cpu_over_wall"] for p in per]),
                    "paced_keys_p50_us": 1e6 * median([p["paced_keys_p50_s"] for p in per]),
                    "paced_keys_p99_us": 1e6 * median([p["paced_keys_p99_s"] for p in per]),
                    "paced_cores_used": median([p["paced_cores_used"] for p in per]),
                    "increment_us": 1e6 * median([p["increment_s"] for p in per]),
                    "counts_us": 1e6 * median([p["counts_s"] for p in per]),
                    "bonus_us": 1e6 * median([p["bonus_s"] for p in per]),
                    "total_us": 1e6 * median(total),
                    "total_over_k64_blas1": ratio_median(total, base_total),
                    "memory_bytes_per_key": median([p["memory_bytes_per_key"] for p in per]),
                }
            )
    return {"rows": COUNT_ROWS, "table_keys": TABLE_KEYS, "table": rows, "runs": runs}


# ------------------------------------------------------------------ 3. cluster vs actors
def cluster_scaling(rounds: int, episodes: int, work: Path) -> dict:
    from bench_e2e import run_cluster, tmp_config

    config = tmp_config(work)
    runs = []
    cases = [1, 2]
    for r, actors in rotating_rounds(rounds, cases):
        d = work / f"cluster-{r}-{actors}"
        load = begin_run(
            d, f"cluster: round {r + 1}/{rounds}, {actors} actor(s), {episodes} episodes"
        )
        res = run_cluster(config, episodes, episodes, actors, d, 120 + episodes * 4)
        res.update(round=r, actors=actors, loadavg_before=load, loadavg_after=os.getloadavg())
        runs.append(res)
    rows = []
    for actors in cases:
        rs = [x for x in runs if x["actors"] == actors]
        base = [next(y for y in runs if y["round"] == x["round"] and y["actors"] == 1) for x in rs]
        roles = sorted({k for x in rs for k in x["cpu_share"]})
        rows.append(
            {
                "actors": actors,
                "steady_steps_per_s": median([x["steady"]["rate"] for x in rs]),
                "e2e_steps_per_s": median([x["e2e_steps_per_s"] for x in rs]),
                "over_1_actor": ratio_median(
                    [x["steady"]["rate"] for x in rs], [b["steady"]["rate"] for b in base]
                ),
                "policy_lag": median([x["learner"]["policy_lag"] for x in rs]),
                "bonus_p50_ms": median([x["learner"]["bonus_p50_ms"] for x in rs]),
                "cpu_share": {k: median([x["cpu_share"].get(k) for x in rs]) for k in roles},
            }
        )
    return {"episodes": episodes, "rounds": rounds, "table": rows, "runs": runs}


# ------------------------------------------------------------------ main
def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "scaling.json")
    parser.add_argument("--quick", action="store_true", help="short runs (~1-2 min)")
    parser.add_argument(
        "--skip", default="", help="comma-separated parts to skip: learner, counting, cluster"
    )
    add_out(parser, "scaling.json")
    parser.add_argument("--_counting", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--budget", type=float, default=0.2, help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._counting:
        Path(args.result).write_text(json.dumps(counting_child(args.budget)))
        return
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    load_before = os.getloadavg()
    result: dict = {
        "command": command(__file__, argv),
        "cores": os.cpu_count(),
        "loadavg_before": load_before,
    }
    with tempfile.TemporaryDirectory(prefix="bench-scaling-") as tmp:
        tmp = Path(tmp)
        if "learner" not in skip:
            result["learner"] = learner_scaling(
                3 if args.quick else 15, 0.05 if args.quick else 0.15
            )
        if "counting" not in skip:
            result["counting"] = counting_scaling(
                1 if args.quick else 3, 0.05 if args.quick else 0.2, tmp
            )
        if "cluster" not in skip:
            result["cluster"] = cluster_scaling(
                1 if args.quick else 2, 20 if args.quick else 80, tmp
            )
    result["loadavg_after"] = os.getloadavg()

    if "learner" in result:
        print(
            "\n1. Learner update vs agents (spread, Cen-MADDPG, batch 100, hidden 400-300, "
            "1 thread)\n"
        )
        print("| learner | N | ms / update | updates/s | time / N=2 time |")
        print("|---|---|---|---|---|")
        for r in result["learner"]["rows"]:
            print(
                f"| {r['learner']} | {r['agents']} | {r['ms_per_update']:.2f} "
                f"| {r['updates_per_s']:.1f} | {r['time_over_n2']:.2f}x |"
            )
    if "counting" in result:
        print(
            f"\n2. Counting a {COUNT_ROWS}-row batch vs k (speaker_listener s||a, 19 dims; "
            f"table of {TABLE_KEYS:,} keys), microseconds; 'cores burnt': CPU seconds of the "
            "process per wall second while it hashes every 8 ms and sleeps in between\n"
        )
        print(
            "| BLAS threads | k | key bytes | SimHash keys | increment "
            "| look-up | keys+increment+look-up | / k=64 (1 thread) "
            "| bonus() (keys+look-up+price) | keys every 8 ms: p50 / p99 µs, cores burnt "
            "| table B/key |"
        )
        print("|" + "---|" * 11)
        for r in result["counting"]["table"]:
            print(
                f"| {r['blas']} | {r['k']} | {r['key_bytes']} | {r['keys_us']:.0f} "
                f"| {r['increment_us']:.0f} "
                f"| {r['counts_us']:.0f} | {r['total_us']:.0f} "
                f"| {r['total_over_k64_blas1']:.2f}x | {r['bonus_us']:.0f} "
                f"| {r['paced_keys_p50_us']:.0f} / {r['paced_keys_p99_us']:.0f}, "
                f"{r['paced_cores_used']:.2f} | {r['memory_bytes_per_key']:.0f} |"
            )
    if "cluster" in result:
        c = result["cluster"]
        print(
            f"\n3. Cluster (`macb up --run`) with 1 vs 2 actors, {c['episodes']} episodes, "
            "evaluation at the end only\n"
        )
        print(
            "| actors | steady steps/s | end-to-end steps/s | / 1 actor | policy lag "
            "| bonus p50 ms | cores used (steady window) |"
        )
        print("|---|---|---|---|---|---|---|")
        for r in c["table"]:
            cpu = ", ".join(f"{k} {v:.2f}" for k, v in r["cpu_share"].items() if v and v >= 0.02)
            print(
                f"| {r['actors']} | {fmt(r['steady_steps_per_s'])} "
                f"| {fmt(r['e2e_steps_per_s'])} | {fmt(r['over_1_actor'], '.2f')}x "
                f"| {fmt(r['policy_lag'], '.2f')} | {fmt(r['bonus_p50_ms'], '.2f')} | {cpu} |"
            )
    write_result(args.out, result, load_before)


if __name__ == "__main__":
    main()
