"""Figure 8's campaign against its update's floor: where a group episode's time goes.

The campaign runs `macb reproduce fig8 --local --profile thesis --arms 'sparse*'`: 12
runs (4 arms x 3 seeds, fp32) as two run groups of 6, one process per core. Variants,
run in the same order every round (A B A B ...: the machine's drift hits each alike):

* `figure`: that command on a scratch folder for --episodes episodes, with
  MACB_GROUP_TIMING set: each group's seconds per part of its loop at every point
  (cli/trainer.py `GroupRun.timing`). Its time per group episode is taken between
  episodes --from and --episodes (after the updates began), and split per training
  step into the update, sampling, pricing, acting and the worlds, storing and
  counting, evaluation, writing rows, cuts and the loop's own rest; with the page
  faults and system seconds of each group's process over the same window.
* `floor`: two probes at once (as the two groups run), each timing the group update's
  floor in the figure's shapes: the products of one update of 6 runs with one
  minibatch per agent (`minibatch: per-agent`, the target actors reading each run's
  two minibatches) plus one in-place pass over weights, targets, gradients and both
  Adam moments (bench_group.py's floor), on one thread.
* `update`: two probes at once, each timing `GroupMADDPG.update` of such a group alone
  on random minibatches: the update outside the figure.
* `figure-glibc-heap` (not run unless asked): `figure` with MACB_STEADY_HEAP=0, malloc's
  thresholds left as glibc moves them (shared/run/heap.py says why that costs).
* `figure-unfused`, `update-unfused` (not run unless asked): `figure` and `update` with
  MACB_FUSED=0, each network's Adam step and its targets' soft update as torch's two
  passes instead of fused.py's one (the same bits).
* `master`, `master-unfused` (not run unless asked): two probes at once, each timing the
  update's master-weight work alone (both networks' Adam steps and the soft update, the
  learner's own `_step` and `soft_update` on fixed gradients), fused and with
  MACB_FUSED=0.

The figure's ratio is its time per training step over the floor's time per update of
the same round. The probes set up their process as a group's (one torch thread, one BLAS
thread, `shared.run.heap.steady_heap`).

    .venv/bin/python benchmarks/bench_fig8.py [--episodes 120] [--from 60] [--rounds 3]
        [--probe-seconds 30] [--variants figure floor update ...] [--py-spy] [--quick]
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

from _harness import RESULTS, command, progress, write_result
from _procs import ROOT, pin_threads

pin_threads()  # before numpy or torch: the probes run one BLAS/OpenMP thread, as the groups

GROUPS = 2  # the campaign's: one group per core
STEP_PARTS = ("update", "sample", "price", "act_env", "store_count", "eval", "rows", "cut")
VARIANTS = (
    "figure", "floor", "update", "figure-glibc-heap", "figure-unfused", "update-unfused",
    "master", "master-unfused",
)  # fmt: skip
FIGURE_ENV = {
    "figure": {},
    "figure-glibc-heap": {"MACB_STEADY_HEAP": "0"},
    "figure-unfused": {"MACB_FUSED": "0"},
}
UNFUSED = {"MACB_FUSED": "0"}
PROBE_ENV = {
    "floor": {},
    "update": {},
    "update-unfused": UNFUSED,
    "master": {},
    "master-unfused": UNFUSED,
}


def cpu() -> str:
    """The CPU's model name, family and model, from /proc/cpuinfo."""
    fields: dict[str, str] = {}
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
        if not line.strip() and fields:
            break
    name = fields.get("model name", "unknown")
    return f"{name} (family {fields.get('cpu family', '?')} model {fields.get('model', '?')})"


def figure_configs() -> list:
    """The figure's 12 run configs as the campaign builds them (fp32, profile thesis)."""
    from cli.local import expand_body
    from cli.reproduce.experiments import experiment_body, file_seeds, select_arms
    from cli.reproduce.figures import FIGURES

    fig = FIGURES["fig8"]
    body = experiment_body(fig, "thesis", file_seeds(fig), None, None)
    body = select_arms(fig, body, ["sparse*"])
    _, _, runs = expand_body(body)
    return [r.config for r in runs]


# ---------------------------------------------------------------- probes
def group_learner(runs: int):
    """A GroupMADDPG of the figure's first `runs` runs, and a random per-agent batch
    (R, N, B, ...) as its groups draw them."""
    import numpy as np

    from shared.core.learners.group import GroupMADDPG
    from shared.envs.tasks import task_spec_for
    from shared.run.factories import agent_dims, learner_spec

    cfgs = figure_configs()[:runs]
    spec = task_spec_for(cfgs[0])
    group = GroupMADDPG(agent_dims(spec), [learner_spec(c) for c in cfgs], precision="fp32")
    rng = np.random.default_rng(0)
    r, n, b = runs, group.n, cfgs[0].batch_size
    o, a = group.joint_obs, group.joint_act
    batch = (
        rng.standard_normal((r, n, b, o)).astype(np.float32),
        rng.uniform(-1, 1, (r, n, b, a)).astype(np.float32),
        rng.uniform(-1, 0, (r, n, b, n)).astype(np.float32),
        rng.standard_normal((r, n, b, o)).astype(np.float32),
        (rng.uniform(0, 1, (r, n, b)) < 0.05).astype(np.float32),
    )
    return group, batch


def probe(kind: str, seconds: float, runs: int) -> dict[str, Any]:
    """In a process of its own: ms per call of the group update's floor or of the
    update itself, in blocks of calls over `seconds` (median and mean of the blocks)."""
    import bench_group
    import torch

    from shared.run.heap import steady_heap

    steady_heap()  # as train_group does
    torch.set_num_threads(1)
    group, batch = group_learner(runs)
    if kind in ("update", "update-unfused"):
        fn = lambda: group.update(*batch)  # noqa: E731
    elif kind in ("master", "master-unfused"):
        group.update(*batch)  # Adam's state exists
        nets = [(group.critic_optim, group.critic), (group.actor_optim, group.actor)]
        grads = [[torch.randn_like(p).mul_(1e-3) for p in s.params] for _, s in nets]

        def fn() -> None:  # what update_on does after the products (batched.py)
            group._soft_in_step = group.stats()["fused"] == 1.0
            for (optim, stack), g in zip(nets, grads):
                group._step(optim, stack.params, g, stack.targets)
            group._soft_in_step = False
            group.soft_update()

    else:
        products, one_pass = bench_group.group_floor(group, target_rows=group.n * 100)

        def fn() -> None:
            products()
            one_pass()

    for _ in range(5):
        fn()
    blocks, end = [], time.perf_counter() + seconds
    while time.perf_counter() < end or len(blocks) < 3:
        t0 = time.perf_counter()
        for _ in range(5):
            fn()
        blocks.append((time.perf_counter() - t0) / 5 * 1e3)
    return {
        "ms": statistics.median(blocks),
        "mean_ms": statistics.mean(blocks),
        "blocks": len(blocks),
        "torch_threads": torch.get_num_threads(),
        "fused": group.stats()["fused"],
    }


def run_probes(kind: str, seconds: float, runs: int) -> dict[str, Any]:
    """GROUPS probes at once; each one's result and their mean."""
    argv = [sys.executable, __file__, "_probe", kind, str(seconds), str(runs)]
    env = {**os.environ, **PROBE_ENV[kind]}
    procs = [
        subprocess.Popen(argv, stdout=subprocess.PIPE, text=True, cwd=ROOT, env=env)
        for _ in range(GROUPS)
    ]
    parts = []
    for p in procs:
        out, _ = p.communicate()
        if p.returncode:
            raise SystemExit(f"the {kind} probe failed ({p.returncode})")
        parts.append(json.loads(out.strip().splitlines()[-1]))
    return {"ms": statistics.mean(x["ms"] for x in parts), "probes": parts}


# ---------------------------------------------------------------- the figure
def figure_argv(episodes: int, out: Path) -> list[str]:
    return [
        sys.executable, "-m", "cli", "reproduce", "fig8", "--local", "--profile", "thesis",
        "--arms", "sparse*", "--episodes", str(episodes), "--group-size", "6",
        "--jobs", str(GROUPS), "--out", str(out), "--quiet",
    ]  # fmt: skip


def window(points: list[dict[str, float]], start: int, end: int) -> dict[str, float]:
    """The differences of every timed quantity between the points at episodes `start`
    and `end` (the first point when `start` precedes it)."""
    at = {p["episode"]: p for p in points}
    if end not in at:
        raise SystemExit(f"no point at episode {end} in the group's timing")
    first = at.get(start, points[0])
    return {k: at[end][k] - first[k] for k in at[end]}


def group_split(data: dict[str, Any], start: int, end: int, steps_per_episode: int):
    """A group's time per episode and its parts in ms per training step."""
    d = window(data["points"], start, end)
    episodes = d["episode"]
    steps = episodes * steps_per_episode
    parts = {k: 1e3 * d[k] / steps for k in STEP_PARTS}
    step_ms = 1e3 * d["wall"] / steps
    parts["loop"] = step_ms - sum(parts.values())
    return {
        "runs": data["runs"],
        "episode_s": d["wall"] / episodes,
        "step_ms": step_ms,
        "parts_ms": parts,
        "minor_faults_per_step": d["minor_faults"] / steps,
        "sys_ms_per_step": 1e3 * d["sys_s"] / steps,
        "user_ms_per_step": 1e3 * d["user_s"] / steps,
        "torch_threads": data["torch_threads"],
        "blas": data["blas"],
    }


def run_figure(args: argparse.Namespace, work: Path, variant: str) -> dict[str, Any]:
    timing = work / "timing"
    env = {**os.environ, "MACB_GROUP_TIMING": str(timing), "PYTHONUNBUFFERED": "1"}
    env.update(FIGURE_ENV[variant])
    argv = figure_argv(args.episodes, work / "fig8")
    if args.py_spy:
        prof = work / "py-spy.txt"
        argv = ["py-spy", "record", "--subprocesses", "--format", "raw", "--rate", "50",
                "--output", str(prof), "--", *argv]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(argv, env=env, cwd=ROOT, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"the figure failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    files = sorted(timing.glob("timing-*.json"))
    if len(files) != GROUPS:
        raise SystemExit(f"expected {GROUPS} groups' timing in {timing}, found {len(files)}")
    steps = figure_configs()[0].episode_len
    groups = [
        group_split(json.loads(f.read_text()), args.start, args.episodes, steps) for f in files
    ]
    result: dict[str, Any] = {
        "episode_s": statistics.mean(g["episode_s"] for g in groups),
        "step_ms": statistics.mean(g["step_ms"] for g in groups),
        "command_wall_s": wall,
        "groups": groups,
    }
    if args.py_spy:
        result["py_spy"] = profile_split(work / "py-spy.txt")
    return result


# Where a sample of the groups' processes is, by the innermost of these frames on its
# stack (the first that matches, in this order).
PROFILE_MARKS = (
    ("update", "update (shared/core/learners/group.py"),
    ("sample", "sample (cli/trainer.py"),
    ("price", "price (cli/trainer.py"),
    ("act_env", "step (shared/run/rollout.py"),
    ("store_count", "collect (cli/trainer.py"),
    ("eval", "evaluate_group"),
    ("cut", "cut (cli/trainer.py"),
    ("loop", "go (cli/trainer.py"),
)


def profile_split(path: Path) -> dict[str, Any]:
    """The shares of py-spy's samples of the groups' processes (those started by the
    process pool) by part of the loop, and the update's 12 hottest lines."""
    import collections

    parts: collections.Counter[str] = collections.Counter()
    lines: collections.Counter[str] = collections.Counter()
    for line in path.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        if "spawn_main" not in stack:
            continue  # the command's own process
        frames = stack.split(";")
        name = next((k for k, mark in PROFILE_MARKS if mark in stack), "start")
        parts[name] += int(n)
        if name == "update":
            lines[frames[-1]] += int(n)
    total = sum(parts.values()) or 1
    return {
        "samples": total,
        "shares": {k: v / total for k, v in parts.most_common()},
        "update_leaves": {k: v / total for k, v in lines.most_common(12)},
    }


# ---------------------------------------------------------------- report
def summarise(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians over rounds; each ratio taken within a round, then its median."""

    def med(xs: list[float]) -> float | None:
        return statistics.median(xs) if xs else None

    def per_call(r: dict[str, Any], v: str) -> float:
        return r[v]["step_ms"] if v in FIGURE_ENV else r[v]["ms"]

    out: dict[str, Any] = {}
    present = [v for v in VARIANTS if any(v in r for r in rounds)]
    for v in present:
        out[v] = {"ms": med([per_call(r, v) for r in rounds if v in r])}
        if v in FIGURE_ENV:
            groups = [g for r in rounds if v in r for g in r[v]["groups"]]
            out[v]["episode_s"] = med([r[v]["episode_s"] for r in rounds if v in r])
            out[v]["parts_ms"] = {
                k: statistics.median(g["parts_ms"][k] for g in groups)
                for k in groups[0]["parts_ms"]
            }
            for k in ("minor_faults_per_step", "sys_ms_per_step", "user_ms_per_step"):
                out[v][k] = statistics.median(g[k] for g in groups)
    ratios = {}
    for a in present:
        for b in present:
            got = [per_call(r, a) / per_call(r, b) for r in rounds if a in r and b in r]
            against_all = a in (
                "figure-glibc-heap", "figure-unfused", "update-unfused", "master-unfused"
            )  # fmt: skip
            if a != b and got and (b in ("floor", "update") or against_all):
                ratios[f"{a} / {b}"] = statistics.median(got)
    out["ratios"] = ratios
    return out


def print_report(s: dict[str, Any], rounds: list[dict[str, Any]], cpu_name: str) -> None:
    present = [v for v in VARIANTS if v in s]
    print("\nms per training step (figures) or per update (probes), two processes at once:")
    print("\n| round | " + " | ".join(present) + " |")
    print("|---" * (len(present) + 1) + "|")
    for i, r in enumerate(rounds, 1):
        cells = []
        for v in present:
            got = r.get(v)
            cells.append("-" if got is None else f"{got.get('step_ms', got.get('ms')):.1f}")
        print(f"| {i} | " + " | ".join(cells) + " |")
    print("\n| ratio (median of the rounds') | |")
    print("|---|---|")
    for k, v in s["ratios"].items():
        print(f"| {k} | {v:.3f}x |")
    for v in (v for v in present if v in FIGURE_ENV):
        got = s[v]
        print(f"\n{v}: {got['episode_s']:.3f} s per group episode, {got['ms']:.1f} ms per step")
        print("\n| part of a training step | ms | share |")
        print("|---|---|---|")
        for k, x in got["parts_ms"].items():
            print(f"| {k} | {x:.2f} | {x / got['ms']:.1%} |")
        print(
            f"\nper step: {got['minor_faults_per_step']:.0f} page faults, "
            f"{got['sys_ms_per_step']:.2f} ms system, {got['user_ms_per_step']:.2f} ms user CPU"
        )
    for r in rounds:
        for v in FIGURE_ENV:
            if "py_spy" in r.get(v, {}):
                shares = r[v]["py_spy"]["shares"]
                print(f"py-spy, {v}: " + ", ".join(f"{k} {x:.1%}" for k, x in shares.items()))
    print(f"\nCPU: {cpu_name}")


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["_probe"]:
        print(json.dumps(probe(argv[1], float(argv[2]), int(argv[3]))))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=120, help="the figure's length")
    parser.add_argument(
        "--from", dest="start", type=int, help="the window's first episode (default half)"
    )
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--probe-seconds", type=float, default=30.0, help="each floor/update probe's length"
    )
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS[:3]))
    parser.add_argument(
        "--py-spy",
        action="store_true",
        help="record the figure with py-spy (on PATH) and report its samples' split",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="a smoke run: --episodes 7 --from 5 --rounds 1 --probe-seconds 1",
    )
    parser.add_argument("--out", type=Path, default=RESULTS / "fig8_speed.json")
    args = parser.parse_args(argv)
    if args.quick:
        args.episodes, args.start, args.rounds, args.probe_seconds = 7, 5, 1, 1.0
    args.start = args.episodes // 2 if args.start is None else args.start
    learning_starts = figure_configs()[0].learning_starts // figure_configs()[0].episode_len
    if not learning_starts <= args.start < args.episodes:
        raise SystemExit(
            f"--from {args.start}: give an episode in [{learning_starts}, {args.episodes}) "
            f"(updates begin after episode {learning_starts})"
        )
    runs = len(figure_configs()) // GROUPS
    load = os.getloadavg()
    rounds: list[dict[str, Any]] = []
    for r in range(args.rounds):
        got: dict[str, Any] = {}
        for variant in args.variants:
            progress(f"round {r + 1}/{args.rounds}: {variant} (load {os.getloadavg()[0]:.2f}) ...")
            if variant in FIGURE_ENV:
                with tempfile.TemporaryDirectory(prefix="bench-fig8-") as tmp:
                    got[variant] = run_figure(args, Path(tmp), variant)
            else:
                got[variant] = run_probes(variant, args.probe_seconds, runs)
            got[variant]["load_after"] = os.getloadavg()[0]
        rounds.append(got)
    summary = summarise(rounds)
    cpu_name = cpu()
    print_report(summary, rounds, cpu_name)
    result = {
        "command": command(__file__, argv),
        "cpu": cpu_name,
        "cores": os.cpu_count(),
        "episodes": args.episodes,
        "from": args.start,
        "summary": summary,
        "rounds": rounds,
    }
    write_result(args.out, result, load)


if __name__ == "__main__":
    main()
