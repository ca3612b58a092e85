"""Run groups: the group update against its floor and one run's learner, and a figure's
runs end to end as one group against the cluster's two slots.

`update` (in this process, rotating rounds, ratios within a round): a group of R
speaker_listener runs (Cen-MADDPG, 400-300, batch 100; Cen-MACB k 512 beta 0.8 prices
their bonuses, which the update does not see) updated by one `GroupMADDPG.update`,
against
* its floor: the group update's matrix products alone (the same shapes, preallocated,
  in the learner's dtype) plus one in-place pass over the group's weights, targets,
  gradients and both Adam moments (fp32: what Adam and the soft update must at least
  read and write), each timed in the same rounds;
* one run's `BatchedMADDPG` alone, in the same precision: run-updates/s of the group
  over the lone learner's updates/s.

`e2e` (whole processes, rotating rounds): figure 8's sparse pair (its sparse Cen-MACB
and sparse Cen-MADDPG arms, 3 seeds each: 6 runs) for --episodes episodes with an
evaluation after every episode (the thesis's protocol), as one run group in one
process (`GroupRun`), against
* `cluster`: `macb up --slots 2` running two seeds of the Cen-MACB arm asynchronously
  (what `macb reproduce --slots 2 --interleave async` runs at a time);
* `cluster-group`: the same six runs as one lockstep run group on the cluster's
  services (router, counter, learner, evaluator, one actor as processes; `start_group`):
  what `macb reproduce` runs through the cluster, each run the group's bit for bit. Its
  rate is the runs' env steps at their last point over the learner's clock then.

`price` (in this process, rotating rounds, ratios within a round): pricing plus
sampling of one group step of figure 8's sparse pair (6 runs, profile thesis: one
minibatch per agent) after --fill transitions of each run, as `GroupRun` does it (each
run's rows drawn from its own sampler, one gather per field over the group's replay,
each row's bonus a gather of the counts at the slots stored when it was counted)
against the per-run way it replaced (each run's minibatches sampled from its own
buffer, their keys SimHashed again and looked up, the parts stacked). Both give the
same arrays, checked bit for bit before timing; the target is <= 1 ms per step.

Each side's rate is run-steps/s: the group's from its own timing, the `cluster`'s total
over its two runs (steady rates, as bench_slots.py takes them). The group's share of
wall time in acting and stepping the worlds and in evaluation is reported; from the
rates, figure 8's headline pair (4.8e6 run-steps: 2 arms x 3 seeds x configs/fig8's 40,000
episodes x 20 steps) in hours.

    .venv/bin/python benchmarks/bench_group.py update [--runs 6] [--rounds 7]
        [--precision fp32 bf16] [--threads 1]
    .venv/bin/python benchmarks/bench_group.py e2e [--episodes 60] [--rounds 3]
        [--precision fp32] [--threads 2] [--cluster [cluster] [cluster-group]]
    .venv/bin/python benchmarks/bench_group.py price [--fill 20000] [--rounds 7]
        [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _harness import FIG8_PAIR_RUN_STEPS, RESULTS, command, progress, write_result
from _procs import ROOT
from _stats import cpu_model, measure, ratio_median, rotating_rounds


# ---------------------------------------------------------------- update
def group_and_alone(runs: int, precision: str):
    import numpy as np

    from shared.core.learners import BatchedMADDPG, LearnerSpec
    from shared.core.learners.group import GroupMADDPG
    from shared.envs.tasks import task_spec
    from shared.run.factories import agent_dims

    dims = agent_dims(task_spec("speaker_listener"))
    specs = [LearnerSpec(algo="cen-maddpg", hidden=(400, 300), seed=s) for s in range(runs)]
    group = GroupMADDPG(dims, specs, precision=precision)
    alone = BatchedMADDPG(dims, specs[0], precision=precision)
    rng = np.random.default_rng(0)
    o, a = alone.joint_obs, alone.joint_act

    def batch(lead):
        return (
            rng.standard_normal((*lead, 100, o)).astype(np.float32),
            rng.uniform(-1, 1, (*lead, 100, a)).astype(np.float32),
            rng.uniform(-1, 0, (*lead, 100, 2)).astype(np.float32),
            rng.standard_normal((*lead, 100, o)).astype(np.float32),
            (rng.uniform(0, 1, (*lead, 100)) < 0.05).astype(np.float32),
        )

    return group, alone, batch((runs,)), batch(())


def group_floor(group, target_rows: int = 100) -> tuple[Any, Any]:
    """(the group update's products, one pass over its state) as two callables;
    `target_rows`: the rows each target actor reads (a run's N minibatches with
    `minibatch: per-agent`, N x 100)."""
    import torch

    from shared.core.learners.layers import linear_forward, linear_grad_input, linear_grad_weight

    dt, rows = group.dtype, 100
    entries = group.runs * group.n

    def layers(params, rows=rows):
        out = []
        for w in params[0::2]:
            w = torch.randn_like(w.detach(), dtype=dt)
            _, fan_out, fan_in = w.shape
            x = torch.randn(entries, rows, fan_in, dtype=dt)
            b = torch.randn(entries, 1, fan_out, dtype=dt)
            g = torch.randn(entries, rows, fan_out, dtype=dt)
            out.append((x, w, b, g))
        return out

    actor, critic = layers(group.actor.params), layers(group.critic.params)
    target_actor = actor if target_rows == rows else layers(group.actor.params, target_rows)
    critic2 = layers(group.critic.params)  # the actor step's critic pass, other inputs

    def forward(ls):
        for x, w, b, _ in ls:
            linear_forward(x, w, b)

    def backward(ls, weights, first_input):
        for k in reversed(range(len(ls))):
            x, w, _, g = ls[k]
            if weights:
                linear_grad_weight(g, x)
            if k > 0 or first_input:
                linear_grad_input(g, w)

    def products() -> None:
        with torch.no_grad():
            forward(target_actor)
            forward(critic)
            forward(critic)
            backward(critic, True, False)
            forward(actor)
            forward(critic2)
            backward(critic2, False, True)
            backward(actor, True, False)

    params = group.actor.params + group.critic.params
    state = [torch.randn_like(p) for p in params for _ in range(5)]

    def one_pass() -> None:
        torch._foreach_mul_(state, 1.0)

    return products, one_pass


def bench_update(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    from shared.core.learners.precision import native_bf16

    torch.set_num_threads(args.threads)
    rows = []
    for precision in args.precision:
        if precision == "bf16" and not native_bf16():
            progress("bf16 skipped: this CPU has no native bf16 (a learner would run fp32)")
            continue
        group, alone, gb, ab = group_and_alone(args.runs, precision)
        products, one_pass = group_floor(group)
        fns = {
            "group": lambda g=group, b=gb: g.update(*b),
            "alone": lambda m=alone, b=ab: m.update(*b),
            "products": products,
            "pass": one_pass,
        }
        progress(f"update, {precision}, {args.runs} runs, {args.threads} thread(s) ...")
        s = measure(fns, args.rounds, 0.4)
        floor = [p + q for p, q in zip(s["products"], s["pass"])]
        row = {
            "precision": group.precision,
            "runs": args.runs,
            "threads": args.threads,
            "group_ms": 1e3 * statistics.median(s["group"]),
            "alone_ms": 1e3 * statistics.median(s["alone"]),
            "products_ms": 1e3 * statistics.median(s["products"]),
            "pass_ms": 1e3 * statistics.median(s["pass"]),
            "group_over_floor": ratio_median(s["group"], floor),
            # run-updates/s of the group over the lone learner's updates/s
            "speedup": ratio_median([a * args.runs for a in s["alone"]], s["group"]),
        }
        rows.append(row)
    print(
        "\n| precision | runs | threads | group update ms | floor ms (products + pass) "
        "| group / floor | one run alone ms | run-updates/s, group / alone |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['precision']} | {r['runs']} | {r['threads']} | {r['group_ms']:.1f} "
            f"| {r['products_ms'] + r['pass_ms']:.1f} ({r['products_ms']:.1f} + "
            f"{r['pass_ms']:.1f}) | {r['group_over_floor']:.2f}x | {r['alone_ms']:.2f} "
            f"| {r['speedup']:.2f}x |"
        )
    return {"rows": rows}


# ---------------------------------------------------------------- e2e
def fig8_pair(opts: dict[str, Any]) -> list:
    """Figure 8's sparse pair: its Cen-MACB and Cen-MADDPG arms, seeds 0-2 (6 runs)."""
    from shared.config import make_config, read_config_file

    cfgs = []
    for arm in ("sparse-cen-macb", "sparse"):
        data = read_config_file(ROOT / "configs" / "fig8" / f"{arm}.yaml")
        data.pop("seeds")
        for seed in (0, 1, 2):
            over = {"seed": seed, "episodes": opts["episodes"], "precision": opts["precision"],
                    "threads": opts["threads"], "interleave": "lockstep",
                    "eval_every": 1}  # fmt: skip
            if "profile" in opts:  # (its presets then fill what the arm does not set)
                over["profile"] = opts["profile"]
            cfgs.append(make_config({**data, **over}))
    return cfgs


# ---------------------------------------------------------------- price
def per_run_step(g: Any, rngs: list) -> list:
    """One group step's update arrays the per-run way (before slots and the group's
    replay): each run samples its minibatches, hashes their keys and looks them up,
    prices and records them, and the parts are stacked."""
    import numpy as np

    from shared.core.replay import update_arrays

    k, size = g.minibatches_per_update, g.cfg.batch_size
    parts = []
    for m, rng in zip(g.members, rngs):
        batches = [m.buffer.sample(size, rng) for _ in range(k)]
        beta = m.cfg.beta_at(m.env_steps)
        bonuses = []
        for b in batches:
            counts = m.explorer.counts(b.obs, b.act)
            bonuses.append(m.explorer.bonus_from_counts(counts, len(b.rew), beta))
            m.diagnostics.record(bonuses[-1], counts)
        parts.append(update_arrays(batches, bonuses))
    return [np.stack(cols) for cols in zip(*parts)]


def group_step(g: Any, rngs: list) -> list:
    """One group step's update arrays as `GroupRun.episode` makes them."""
    k, size = g.minibatches_per_update, g.cfg.batch_size
    idx = g.replay.draw(size, k, rngs)
    bonuses = [m.price(idx[r]) for r, m in enumerate(g.members)]
    return g.update_arrays(idx, bonuses, [True] * len(g.members))


def filled_group(fill: int) -> Any:
    """Figure 8's sparse pair (profile thesis) as a `GroupRun`, each run's replay and
    tables filled with `fill` transitions of its own (acting with the untrained policy
    and its noise; no update)."""
    from cli.trainer import GroupRun

    opts = {"episodes": 40_000, "precision": "fp32", "threads": 1, "profile": "thesis"}
    cfgs = fig8_pair(opts)
    g = GroupRun(cfgs, [None] * len(cfgs), 60.0)
    for _ in range(fill):
        tr = g.collector.step(g.learner.act)
        for r, m in enumerate(g.members):
            m.collect(tr.obs[r], tr.act[r], float(tr.rew[r]), tr.next_obs[r],
                      float(tr.done[r]), int(tr.collisions[r]))  # fmt: skip
    return g


def bench_price(args: argparse.Namespace) -> dict[str, Any]:
    import numpy as np
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    with threadpool_limits(limits=1, user_api="blas"):  # as train_group runs
        progress(f"filling 6 runs' replay with {args.fill} transitions each ...")
        g = filled_group(args.fill)
        cfg = g.cfg
        assert cfg.profile == "thesis"

        def rngs(seed: int) -> list:
            return [np.random.default_rng([seed, r]) for r in range(g.runs)]

        a, b = per_run_step(g, rngs(0)), group_step(g, rngs(0))
        same = all(x.dtype == y.dtype and np.array_equal(x, y) for x, y in zip(a, b))
        if not same:
            raise SystemExit("bench_group price: the two ways give different arrays")
        ours, theirs = rngs(1), rngs(1)
        fns = {
            "group": lambda: group_step(g, ours),
            "per_run": lambda: per_run_step(g, theirs),
        }
        progress(f"pricing + sampling, {g.runs} runs, {args.rounds} rounds ...")
        s = measure(fns, args.rounds, 0.05 if args.quick else 0.4)
    row = {
        "runs": g.runs,
        "profile": cfg.profile,
        "minibatches": g.minibatches_per_update,
        "batch": cfg.batch_size,
        "fill": args.fill,
        "group_ms": 1e3 * statistics.median(s["group"]),
        "per_run_ms": 1e3 * statistics.median(s["per_run"]),
        "per_run_over_group": ratio_median(s["per_run"], s["group"]),
        "same_arrays": same,
    }
    row["within_target"] = row["group_ms"] <= 1.0
    target = "yes" if row["within_target"] else "no"
    print("\n| runs | profile | minibatches x rows | filled | group step ms | per-run ms "
          "| per-run / group | <= 1 ms |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    print(f"| {row['runs']} | {row['profile']} | {row['minibatches']} x {row['batch']} "
          f"| {row['fill']:,} | {row['group_ms']:.3f} | {row['per_run_ms']:.3f} "
          f"| {row['per_run_over_group']:.1f}x | {target} |")  # fmt: skip
    return {"rows": [row]}


def group_child(spec: str) -> None:
    """In a process of its own: the group run of `spec` (JSON), its rate and shares."""
    opts = json.loads(spec)
    from cli.trainer import GroupRun

    cfgs = fig8_pair(opts)
    jobs, job = opts.get("jobs", 1), opts.get("job", 0)
    cfgs = cfgs[job::jobs]  # this process's share of the six runs
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):  # as train_group runs
        g = GroupRun(cfgs, [None] * len(cfgs), 60.0)
        g.start = time.perf_counter()
        for episode in range(1, opts["episodes"] + 1):
            g.episode()
            g.point(episode)
        wall = time.perf_counter() - g.start
    steps = sum(m.env_steps for m in g.members)
    print(json.dumps({"run_steps_per_s": steps / wall, "wall_s": wall, "timing": g.timing,
                      "precision": "bf16" if g.learner.stats()["bf16"] else "fp32"}))  # fmt: skip


def cluster_rate(args: argparse.Namespace, work: Path) -> float:
    """Two seeds of fig8's sparse Cen-MACB through `macb up --slots 2`: total steady
    run-steps/s (bench_slots.py's variant)."""
    import bench_slots

    ns = argparse.Namespace(
        config=ROOT / "configs" / "fig8" / "sparse-cen-macb.yaml",
        episodes=args.episodes,
        precision=args.precision,
    )
    return float(bench_slots.run_variant(2, ns, work)["total"])


def cluster_group_rate(args: argparse.Namespace, work: Path) -> dict[str, float]:
    """The six runs as one lockstep group on the cluster's services."""
    from _harness import Services

    from cli.supervisor import cluster_plan, free_port
    from shared.net.bus import Bus
    from shared.net.control import discover, start_group

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    plan = cluster_plan(1, endpoint, str(work / "data"), api=None)
    services = Services(plan, work / "logs")
    services.start()
    try:
        with Bus([endpoint]) as bus:
            deadline = time.monotonic() + 120
            while len(discover(bus)) < 4:
                if time.monotonic() > deadline:
                    raise SystemExit(f"the cluster's services did not come up ({work / 'logs'})")
                time.sleep(0.2)
            cfgs = fig8_pair({"episodes": args.episodes, "precision": args.precision,
                              "threads": args.threads})  # fmt: skip
            t0 = time.monotonic()
            watches = start_group(bus, cfgs)
            for w in watches:
                if w.wait(timeout=3600) != "completed":
                    raise SystemExit(f"a run of the group ended {w.state()}: {w.states}")
            wall = time.monotonic() - t0
            last = [max(w.rows, key=lambda r: r["episode"]) for w in watches]
    finally:
        services.stop()
    steps = sum(r["env_steps"] for r in last)
    return {"run_steps_per_s": steps / max(r["wall_s"] for r in last), "command_wall_s": wall}


def bench_e2e(args: argparse.Namespace) -> dict[str, Any]:
    spec = json.dumps(
        {"episodes": args.episodes, "precision": args.precision, "threads": args.threads}
    )
    if 6 % args.jobs:
        raise SystemExit("--jobs must divide the 6 runs (1, 2, 3 or 6)")
    cases = ["group"] + [c for c in ("cluster", "cluster-group") if c in args.cluster]
    got: dict[str, list] = {c: [] for c in cases}
    for r, case in rotating_rounds(args.rounds, cases):
        progress(f"e2e round {r + 1}/{args.rounds}: {case} (load {os.getloadavg()[0]:.2f}) ...")
        if case == "group":
            procs = [
                subprocess.Popen(
                    [
                        sys.executable,
                        __file__,
                        "_group",
                        json.dumps({**json.loads(spec), "jobs": args.jobs, "job": j}),
                    ],
                    stdout=subprocess.PIPE,
                    text=True,
                    cwd=ROOT,
                )  # fmt: skip
                for j in range(args.jobs)
            ]
            parts = []
            for p in procs:
                out, _ = p.communicate()
                if p.returncode:
                    raise SystemExit(f"the group process failed ({p.returncode})")
                parts.append(json.loads(out.strip().splitlines()[-1]))
            got["group"].append(
                {
                    "run_steps_per_s": sum(x["run_steps_per_s"] for x in parts),
                    "wall_s": max(x["wall_s"] for x in parts),
                    "timing": {
                        k: sum(x["timing"][k] for x in parts) / len(parts)
                        for k in parts[0]["timing"]
                    },
                    "precision": parts[0]["precision"],
                }
            )
        elif case == "cluster":
            with tempfile.TemporaryDirectory(prefix="bench-group-") as tmp:
                got["cluster"].append(cluster_rate(args, Path(tmp)))
        else:
            with tempfile.TemporaryDirectory(prefix="bench-group-") as tmp:
                got["cluster-group"].append(cluster_group_rate(args, Path(tmp)))
    rates = [g["run_steps_per_s"] for g in got["group"]]
    shares = {
        k: statistics.median(g["timing"][k] / g["wall_s"] for g in got["group"])
        for k in got["group"][0]["timing"]
    }
    row: dict[str, Any] = {
        "episodes": args.episodes,
        "precision": got["group"][0]["precision"],
        "threads": args.threads,
        "jobs": args.jobs,
        "group_run_steps_per_s": statistics.median(rates),
        "shares": shares,
        "env_and_eval_share": statistics.median(
            (g["timing"]["act_env"] + g["timing"]["eval"]) / g["wall_s"] for g in got["group"]
        ),
        "fig8_pair_hours_group": FIG8_PAIR_RUN_STEPS / statistics.median(rates) / 3600,
    }
    if got.get("cluster-group"):
        lock = [g["run_steps_per_s"] for g in got["cluster-group"]]
        row["cluster_group_run_steps_per_s"] = statistics.median(lock)
        row["cluster_group_over_group"] = ratio_median(lock, rates)
        row["cluster_group_wall_s"] = statistics.median(
            g["command_wall_s"] for g in got["cluster-group"]
        )
        row["group_wall_s"] = statistics.median(g["wall_s"] for g in got["group"])
        print(
            f"\nlockstep group on the cluster: {row['cluster_group_run_steps_per_s']:.0f} "
            f"run-steps/s, {row['cluster_group_over_group']:.2f}x the one-process group's "
            f"({row['group_run_steps_per_s']:.0f}); wall {row['cluster_group_wall_s']:.1f} s "
            f"(start to the last run's end) vs the group's loop {row['group_wall_s']:.1f} s"
        )
    if got.get("cluster"):
        row["cluster_run_steps_per_s"] = statistics.median(got["cluster"])
        row["group_over_cluster"] = ratio_median(rates, got["cluster"])
        row["fig8_pair_hours_cluster"] = FIG8_PAIR_RUN_STEPS / row["cluster_run_steps_per_s"] / 3600
    print(
        "\n| precision | processes x threads | group run-steps/s | cluster --slots 2 "
        "run-steps/s | group / cluster | act+env+eval share | fig8 pair, hours (group) |"
    )
    print("|---|---|---|---|---|---|---|")
    print(
        f"| {row['precision']} | {args.jobs} x {args.threads} | {row['group_run_steps_per_s']:.0f} "
        f"| {row.get('cluster_run_steps_per_s', float('nan')):.0f} "
        f"| {row.get('group_over_cluster', float('nan')):.2f}x "
        f"| {row['env_and_eval_share']:.1%} | {row['fig8_pair_hours_group']:.2f} |"
    )
    print(
        "shares of the group's wall time: " + ", ".join(f"{k} {v:.1%}" for k, v in shares.items())
    )
    return {"rows": [row]}


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["_group"]:
        group_child(argv[1])
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="part", required=True)
    up = sub.add_parser("update", help="the group update vs its floor and one run alone")
    up.add_argument("--runs", type=int, default=6)
    up.add_argument("--rounds", type=int, default=7)
    up.add_argument("--threads", type=int, default=1)
    up.add_argument("--precision", nargs="+", default=["fp32", "bf16"])
    e2e = sub.add_parser("e2e", help="fig8's sparse pair as one group vs the cluster")
    e2e.add_argument("--episodes", type=int, default=60)
    e2e.add_argument("--rounds", type=int, default=3)
    e2e.add_argument("--threads", type=int, default=2)
    e2e.add_argument("--precision", default="fp32")
    e2e.add_argument(
        "--cluster", nargs="*", default=["cluster", "cluster-group"],
        choices=["cluster", "cluster-group"],
        help="the cluster variants beside the one-process group (none: the group alone)",
    )  # fmt: skip
    e2e.add_argument(
        "--jobs", type=int, default=1,
        help="the six runs as this many groups, one process each (each with --threads)",
    )  # fmt: skip
    pr = sub.add_parser("price", help="pricing + sampling of one fig8 group step")
    pr.add_argument("--fill", type=int, default=20_000, help="transitions in each run's replay")
    pr.add_argument("--rounds", type=int, default=7)
    pr.add_argument("--quick", action="store_true", help="short rounds (a smoke run)")
    for p in (up, e2e, pr):
        p.add_argument("--out", type=Path, help="JSON results (default benchmarks/results/)")
    args = parser.parse_args(argv)
    load = os.getloadavg()
    parts = {"update": bench_update, "e2e": bench_e2e, "price": bench_price}
    result = parts[args.part](args)
    result.update(command=command(__file__, argv), cpu=cpu_model(), cores=os.cpu_count())
    print(f"CPU: {result['cpu']} ({result['cores']} cores)")
    write_result(args.out or RESULTS / f"group_{args.part}.json", result, load)


if __name__ == "__main__":
    main()
