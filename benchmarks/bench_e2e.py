"""End-to-end training throughput: the one-process trainer against the local cluster.

The workload is the thesis's speaker_listener arm: Cen-MADDPG + Cen-MACB, k=512,
beta=0.8, batch 100, hidden 400-300, one update per environment step, 10 noise-free
evaluation episodes per evaluation point. Each variant is a fresh process tree:

* `trainer`: `cli.trainer.train` (what `macb train` runs) in a child process whose
  environment has no OMP/OPENBLAS/MKL_NUM_THREADS, as from a plain shell;
* `trainer-blas1`: the same with those set to 1, which is what `macb up` gives each
  service (cli/supervisor.py THREAD_ENV): the like-for-like baseline for the cluster;
* `cluster`: `macb up --run CONFIG --actors 1 --quiet --quiet-services` on a free
  loopback port (router, counter, learner, evaluator, one actor as processes), watched
  from this process over the bus (learner stats every second, status, metric rows).

each with evaluation on (`--eval-every 1`) and off (`--eval-every` = episodes).

Throughput is updates (= env steps past `learning_starts`, one update per step) per
second in steady state: from the point where a third of the run's updates are done to
the end of training. For the trainer the child records the time at every episode end
(evaluation time falls inside the window, as in `steps_per_sec`); for the cluster the
learner's own `updates` and `wall_s` (published every second, and at completion). For
evaluation-on runs the same is also computed from the metric rows (env_steps and wall_s
of a late evaluation point and the last one), and the overall average of the last row
is reported too. End-to-end time runs until the last metric row exists (for the
cluster: until the evaluator has evaluated the last point).

Variants run in rounds, in a rotating order, one at a time (never two at once): load
from other processes hits them alike; ratios (cluster / trainer) are taken within a
round, and everything is the median over rounds. CPU seconds of every process (from
/proc) show what limits throughput. Just before and after each run a child process
(floor_probe.py) times the update's matrix products alone (bench_learner's floor) on one
and two threads: the machine's speed for this workload then (the host is shared with other
guests), and `steady / floor`, the share of it the run turned into env steps.

    .venv/bin/python benchmarks/bench_e2e.py [--quick]

prints markdown tables and writes benchmarks/results/e2e.json.
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

from _harness import (
    Services,
    TimedWatch,
    add_out,
    begin_run,
    bench_parser,
    command,
    macb_argv,
    progress,
    write_result,
)
from _procs import ROOT, THREAD_VARS, CpuSampler, end, kill_ours, start, thread_env
from _stats import fmt, median, rotating_rounds, top_tottime

from cli.supervisor import THREAD_ENV, cluster_plan, free_port, wait_port
from shared.config import load_config
from shared.net.bus import Bus
from shared.net.control import discover, start_run

CONFIG_YAML = """\
# bench_e2e: thesis figure 8 arm sparse-cen-macb with the appendix A settings.
task: speaker_listener
algo: cen-maddpg
explore: cen-macb
beta: 0.8
k: 512
batch_size: 100
hidden: [400, 300]
eval_episodes: 10
seed: 0
"""
TARGET_CLUSTER_EVAL_ON = 136.0  # steps/s, the issue's target for the cluster, eval on
TARGET_RATIO = 0.85  # cluster within 15% of the trainer
THESIS_STEPS_PER_S = {"with bonus": 34.0, "without bonus": 70.0}
ABOUT = (  # what --help adds to the docstring's first paragraph
    " speaker_listener, Cen-MADDPG + Cen-MACB (k=512, beta=0.8), batch 100, hidden "
    "400-300; evaluation every episode and only at the end."
)
# Fixed learner modes instead of `learner_lanes: auto`: what the config adds.
FIXED_MODES = {
    "-1lane": "learner_lanes: 1\n",  # one thread in the update
    "-2threads": "learner_lanes: 1\nthreads: 2\n",  # torch's two intra-op threads
    # The thesis's loop over the bus (central inference); the trainer runs that loop
    # anyway, so trainer-lockstep is trainer-1lane again, in the same round.
    "-lockstep": "learner_lanes: 1\ninterleave: lockstep\n",
}
VARIANTS = ("trainer", "trainer-blas1", "cluster") + tuple(
    f"{v}{m}" for m in FIXED_MODES for v in ("trainer", "cluster")
)
DEFAULT_VARIANTS = ("trainer-blas1", "cluster", "trainer-1lane", "cluster-1lane")
# What each cluster variant is compared with (same config, same round).
BASELINES = (
    {"cluster": ("trainer-blas1", "trainer")}
    | {f"cluster{m}": (f"trainer{m}",) for m in FIXED_MODES}
    | {"cluster-lockstep": ("trainer-lockstep", "trainer-1lane")}
)


# ------------------------------------------------------------------ steady state
def window_rate(points: list[tuple[float, float]], total: float) -> dict:
    """Steady state from (time_s, updates) samples: from the first sample with at least a
    third of `total` updates to the last sample."""
    points = sorted(points)
    late = [p for p in points if p[1] >= total / 3]
    if len(late) < 2 or late[-1][0] <= late[0][0]:
        return {"rate": None}
    (t0, u0), (t1, u1) = late[0], late[-1]
    return {
        "rate": (u1 - u0) / (t1 - t0),
        "from_updates": u0,
        "to_updates": u1,
        "s": t1 - t0,
        "t0": t0,
        "t1": t1,
    }


def rows_rate(rows: list[dict], episodes: int) -> float | None:
    """env_steps / wall_s between the first row at or past a third of the run and the last."""
    late = [r for r in rows if r["episode"] >= episodes / 3]
    if len(late) < 2:
        return None
    a, b = late[0], late[-1]
    return (b["env_steps"] - a["env_steps"]) / (b["wall_s"] - a["wall_s"])


# ------------------------------------------------------------------ trainer child
def trainer_child(args: argparse.Namespace) -> None:
    """Run the one-process trainer; record the time of every episode end."""
    import resource

    import cli.trainer as trainer_mod  # torch: only in this child, never the parent
    import shared.run.rollout as rollout_mod

    cfg = load_config(args.config, {"episodes": args.episodes, "eval_every": args.eval_every})
    marks: list[tuple[float, float]] = []  # (wall, CPU seconds of all threads)

    class TimedCollector(rollout_mod.Collector):
        def step(self, policy):
            tr = super().step(policy)
            if tr.episode_end:
                marks.append((time.perf_counter(), time.process_time()))
            return tr

    # measurement only: one append per episode (the trainer builds its collector with
    # shared.run.rollout.make_collector, which looks the class up there)
    rollout_mod.Collector = TimedCollector
    t0 = time.perf_counter()
    rows = trainer_mod.train(cfg, Path(args.result).parent / "trainer-out", progress=False)
    wall = time.perf_counter() - t0
    usage = resource.getrusage(resource.RUSAGE_SELF)
    Path(args.result).write_text(
        json.dumps(
            {
                "rows": rows,
                "marks": [(m - t0, c) for m, c in marks],
                "wall_s": wall,
                "cpu_s": usage.ru_utime + usage.ru_stime,
                "learning_starts": cfg.learning_starts,
                "episode_len": cfg.episode_len,
                "env": {k: os.environ.get(k) for k in THREAD_VARS},
            }
        )
    )


def trainer_argv(config: Path, episodes: int, eval_every: int, result: Path) -> list[str]:
    """This script as the trainer child (after the interpreter and its options)."""
    argv = [str(Path(__file__).resolve()), "--_trainer", "--config", str(config)]
    argv += ["--episodes", str(episodes), "--eval-every", str(eval_every)]
    return argv + ["--result", str(result)]


def run_trainer(
    config: Path, episodes: int, eval_every: int, blas1: bool, work: Path, timeout: float
) -> dict:
    result = work / "trainer.json"
    argv = [sys.executable, *trainer_argv(config, episodes, eval_every, result)]
    p = start(argv, work / "trainer.log", thread_env(blas1))
    try:
        p.wait(timeout=timeout)
    finally:
        end(p)
    if p.returncode != 0 or not result.exists():
        raise RuntimeError(f"trainer failed ({p.returncode}); see {work}/trainer.log")
    data = json.loads(result.read_text())
    rows, marks = data["rows"], data["marks"]
    ls, el = data["learning_starts"], data["episode_len"]
    # (time, updates done) at each episode end: updates = steps past learning_starts.
    points = [(t, max(0, (i + 1) * el - ls)) for i, (t, _) in enumerate(marks)]
    total = max(0, episodes * el - ls)
    steady = window_rate(points, total)
    cpu_at = dict(marks)
    steady_cpu = (
        (cpu_at[steady["t1"]] - cpu_at[steady["t0"]]) / steady["s"] if steady["rate"] else None
    )
    last = rows[-1]
    return {
        "steady": steady,
        "rows_steady": rows_rate(rows, episodes) if eval_every < episodes else None,
        "overall_steps_per_sec": last["steps_per_sec"],
        "overall_train_steps_per_sec": last["train_steps_per_sec"],
        "e2e_s": last["wall_s"],
        "e2e_steps_per_s": last["env_steps"] / last["wall_s"],
        "cpu_s": {"trainer": data["cpu_s"]},
        "cpu_share": {"trainer": steady_cpu},  # cores used in the steady window
        "rows": len(rows),
        "final_success": last["success_rate"],
        "env": data["env"],
    }


# ------------------------------------------------------------------ cluster
def up_argv(
    config: Path, episodes: int, eval_every: int, actors: int, work: Path, extra: tuple = ()
):
    """The `macb up --run` command line on free loopback ports, and its endpoint (`extra`:
    more `macb up` flags; with `--secrets` the cluster's endpoint is tls/)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = macb_argv("up", "--run", str(config), "--out", str(work / "cluster-out"))
    argv += ["--endpoint", endpoint, "--data-dir", str(work / "cluster-data")]
    argv += ["--actors", str(actors), "--quiet", "--quiet-services"]
    argv += ["--episodes", str(episodes), "--eval-every", str(eval_every)]
    argv += ["--api-port", str(free_port())]  # never the default port 8000: it may be taken
    argv += list(extra)
    if "--secrets" in extra:
        endpoint = "tls/" + endpoint.removeprefix("tcp/")
    return argv, endpoint


def run_cluster(
    config: Path,
    episodes: int,
    eval_every: int,
    actors: int,
    work: Path,
    timeout: float,
    extra: tuple = (),
) -> dict:
    argv, endpoint = up_argv(config, episodes, eval_every, actors, work, extra)
    t_launch = time.monotonic()
    p = start(argv, work / "up.log", thread_env(False))
    sampler = CpuSampler(p.pid)
    sampler.start()
    watch = None
    try:
        try:
            wait_port(endpoint, 60)
        except TimeoutError as err:
            raise RuntimeError(f"the cluster's router did not listen; see {work}/up.log") from err
        watch = TimedWatch(endpoint)
        p.wait(timeout=timeout)
    finally:
        sampler.stop()
        end(p)
        kill_ours(list(sampler.cpu), (endpoint, str(work)))  # `macb up` ends them; make sure
        if watch is not None:
            watch.close()
    t_exit = time.monotonic()
    if p.returncode != 0:
        raise RuntimeError(f"macb up exited {p.returncode}; see {work}/up.log")
    learner = watch.metric_times.get("learner", [])  # (arrival, learner stats)
    if not learner:
        raise RuntimeError("no learner metrics seen")
    total = learner[-1][1]["updates"]
    points = [(d["wall_s"], d["updates"]) for _, d in learner]
    eval_rows = watch.metric_times.get("eval", [])
    rows = [d for _, d in eval_rows]
    last = learner[-1][1]
    status = [x for seen in watch.status_times.values() for x in seen]
    starts = [t for t, st in status if st["state"] == "running"]
    t_start = min(starts) if starts else t_launch
    t_last_row = max(t for t, _ in eval_rows)
    t_learner_done = learner[-1][0]
    counter = watch.latest.get("counter", {})
    run_s = t_last_row - t_start
    steady = window_rate(points, total)
    share: dict[str, float] = {}
    if steady["rate"]:
        # The steady window in this process's clock: when those learner stats arrived.
        arrival = {d["wall_s"]: t for t, d in learner}
        share = sampler.share(arrival[steady["t0"]], arrival[steady["t1"]])
    return {
        "steady": steady,
        "rows_steady": rows_rate(rows, episodes) if eval_every < episodes else None,
        "overall_steps_per_sec": rows[-1]["steps_per_sec"] if rows else None,
        "e2e_s": run_s,
        "e2e_steps_per_s": episodes * 20 / run_s,
        "startup_s": t_start - t_launch,
        "teardown_s": t_exit - t_last_row,
        "evaluator_lag_s": t_last_row - t_learner_done,
        "learner": {
            k: last.get(k)
            for k in (
                "updates",
                "ingested",
                "wall_s",
                "replay_ratio",
                "policy_lag",
                "bonus_p50_ms",
                "bonus_p99_ms",
                "bonus_failures",
                "bonus_wait_ms_per_update",
                "bonus_queries",
                "bonus_rows_per_query",
                "backlog",
            )
        }
        # how the update ran: learner_lanes auto's picks (share of updates, ms each)
        | {
            k: v
            for k, v in last.items()
            if k.startswith(("lanes", "contended_")) or k in ("threads", "eval_rows_seen")
        }
        # where the learner's wall time went, ms per update by phase
        | {k: v for k, v in last.items() if k.startswith("ms_per_update_")},
        "counter": {
            k: counter.get(k)
            for k in ("counted_transitions", "query_p50_ms", "query_p99_ms", "queries")
        },
        "actors": {k: v for k, v in watch.latest.items() if k.startswith("actor/")},
        "cpu_s": sampler.by_role(),
        "cpu_share": share,  # cores used by each service in the steady window
        "rows": len(rows),
        "final_success": rows[-1]["success_rate"] if rows else None,
        "argv": argv[1:],
    }


# ------------------------------------------------------------------ profiles
TRAINER_PARTS = {
    "learner.update": ("learners/tuning.py", "update"),
    "bonus (hash + look-up)": ("exploration.py", "counts"),
    "count (observe)": ("exploration.py", "observe"),
    "replay sample": ("replay.py", "sample"),
    "env step + act (Collector.step)": ("rollout.py", "step"),
    "evaluation": ("rollout.py", "evaluate"),
}
LEARNER_PARTS = {
    "learner.update": ("learners/tuning.py", "update"),
    "bonus query round trip (BonusClient.bonus_for)": ("learner/main.py", "bonus_for"),
    "replay sample": ("replay.py", "sample"),
    "weights out (Outbound.weights)": ("learner/outbound.py", "weights"),
    "  of which counter stats query": ("learner/outbound.py", "counter_stats"),
    "inbound messages (handle)": ("learner/main.py", "handle"),
    "waiting for messages (inbox get)": ("queue.py", "get"),
}


def profile_parts(path: Path, parts: dict, top: int = 20) -> dict:
    """Cumulative seconds of the named functions, and the top functions by own time."""
    import pstats

    st = pstats.Stats(str(path))
    found = {}
    for label, (file_part, func) in parts.items():
        found[label] = sum(
            v[3] for (f, _, fn), v in st.stats.items() if fn == func and f.endswith(file_part)
        )
    # The run itself (train / serve_forever), not the imports before it.
    total = max(
        (v[3] for (f, _, fn), v in st.stats.items() if fn in ("train", "serve_forever")),
        default=max(v[3] for v in st.stats.values()),
    )
    return {"total_s": total, "parts_s": found, "top_tottime": top_tottime(path, top)}


def profile_trainer(
    config: Path, episodes: int, eval_every: int, work: Path, blas1: bool = True
) -> dict:
    result, prof = work / "trainer.json", work / "trainer.prof"
    argv = [sys.executable, "-m", "cProfile", "-o", str(prof)]
    argv += trainer_argv(config, episodes, eval_every, result)
    p = start(argv, work / "trainer.log", thread_env(blas1))
    try:
        p.wait(timeout=120 + episodes * 4)
    finally:
        end(p)
    return profile_parts(prof, TRAINER_PARTS)


def profile_cluster(config: Path, episodes: int, eval_every: int, work: Path) -> dict:
    """The cluster's services as `macb up` starts them (no API), with the learner under
    cProfile; the run is started on the bus (shared.net.control.start_run)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    plan = cluster_plan(1, endpoint, str(work / "data"), api=None)
    prof = work / "learner.prof"
    services = Services(plan, work, profile={"learner": prof})
    try:
        services.start()
        cfg = load_config(config, {"episodes": episodes, "eval_every": eval_every})
        with Bus([endpoint]) as bus:
            deadline = time.monotonic() + 90
            while len(discover(bus)) < len(plan) - 1:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"services did not come up; logs in {work}")
                time.sleep(0.2)
            watch = start_run(bus, cfg, actors=1)
            state = watch.wait(timeout=120 + episodes * 4)
            if state != "completed":
                raise RuntimeError(f"profiled run {state}: {watch.failure()}")
    finally:
        services.stop()
    return profile_parts(prof, LEARNER_PARTS)


def run_profiles(config: Path, episodes: int, tmp: Path) -> dict:
    out = {}

    def trainer_default(*a):
        return profile_trainer(*a, blas1=False)

    for name, fn in (
        ("trainer", trainer_default),
        ("trainer-blas1", profile_trainer),
        ("cluster learner", profile_cluster),
    ):
        work = tmp / f"profile-{name.replace(' ', '-')}"
        work.mkdir()
        progress(f"profiling {name} (eval off, {episodes} episodes) ...")
        out[name] = fn(config, episodes, episodes, work)
    print("\nProfiles (cProfile, eval off; seconds of the profiled thread, inflated by the")
    print("profiler's own cost):\n")
    print("| part | seconds | share |")
    print("|---|---|---|")
    for name, res in out.items():
        print(f"| **{name}** (total {res['total_s']:.1f} s) | | |")
        for label, sec in res["parts_s"].items():
            print(f"| {label} | {sec:.2f} | {sec / res['total_s']:.0%} |")
    for name, res in out.items():
        print(f"\n{name}, top functions by own time:\n{res['top_tottime']}")
    return out


# ------------------------------------------------------------------ main
def ratio_pair(s: dict, base: str) -> str:
    if f"over_{base}" not in s:
        return "-"
    return f"{fmt(s[f'over_{base}'], '.2f')}, {fmt(s[f'e2e_over_{base}'], '.2f')}"


def tmp_config(tmp: Path) -> Path:
    config = tmp / "config.yaml"
    config.write_text(CONFIG_YAML)
    for mode, extra in FIXED_MODES.items():
        (tmp / f"config{mode}.yaml").write_text(CONFIG_YAML + extra)
    return config


def floor_rates(seconds: float = 0.7) -> dict[str, float] | None:
    """Updates/s of the speaker_listener update's matrix products alone, on 1 and 2
    threads ({"1": .., "2": ..}): floor_probe.py, in a child so this process loads no
    torch: the machine's speed for this workload around a run."""
    env = {**os.environ, **THREAD_ENV}
    try:
        out = subprocess.run(
            [sys.executable, str(Path(__file__).with_name("floor_probe.py")), str(seconds)],
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
            check=True,
            cwd=ROOT,
        )
        return json.loads(out.stdout)
    except (subprocess.SubprocessError, ValueError) as err:
        progress(f"  floor probe failed: {err}")
        return None


def run_variant(name: str, config: Path, episodes: int, ev: int, work: Path) -> dict:
    """`*-1lane`, `*-2threads`: the same with a fixed learner mode (FIXED_MODES); the
    trainer side with one BLAS thread outside torch, as trainer-blas1."""
    timeout = 120 + episodes * 20 / 5.0  # a run slower than 5 steps/s is broken
    for mode in FIXED_MODES:
        if name.endswith(mode):
            config = config.with_name(f"config{mode}.yaml")
            name = {"trainer": "trainer-blas1", "cluster": "cluster"}[name.removesuffix(mode)]
    if name == "cluster":
        return run_cluster(config, episodes, ev, 1, work, timeout)
    return run_trainer(config, episodes, ev, name == "trainer-blas1", work, timeout)


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "e2e.json", ABOUT)
    parser.add_argument("--quick", action="store_true", help="30 episodes, 1 round (~1-2 min)")
    parser.add_argument("--episodes", type=int, default=None, help="per run (default 150)")
    parser.add_argument("--rounds", type=int, default=None, help="rounds (default 2; quick 1)")
    parser.add_argument(
        "--variants",
        default=",".join(DEFAULT_VARIANTS),
        help=f"comma-separated subset of {','.join(VARIANTS)} (default: "
        f"{','.join(DEFAULT_VARIANTS)}; '-1lane': learner_lanes 1; '-2threads': "
        "learner_lanes 1 with two torch threads; '-lockstep': learner_lanes 1 and "
        "interleave lockstep; 'trainer': the environment's default "
        "BLAS/OpenMP thread variables, as a library user who calls cli.trainer.train "
        "gets; train() limits numpy's BLAS to one thread itself since session 3)",
    )
    parser.add_argument(
        "--eval",
        choices=("both", "on", "off"),
        default="both",
        help="per-episode evaluation on, off (only at the end) or both (default)",
    )
    parser.add_argument(
        "--profile",
        action="store_true",
        help="also profile (cProfile) both trainers and the cluster's learner, eval off",
    )
    parser.add_argument(
        "--profile-episodes", type=int, default=80, help="episodes of each profiled run"
    )
    add_out(parser, "e2e.json")
    parser.add_argument("--_trainer", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--config", help=argparse.SUPPRESS)
    parser.add_argument("--eval-every", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._trainer:
        trainer_child(args)
        return

    episodes = args.episodes or (30 if args.quick else 150)
    rounds = args.rounds or (1 if args.quick else 2)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    if unknown := set(variants) - set(VARIANTS):
        parser.error(f"unknown variants {sorted(unknown)}")
    evals = {k: v for k, v in {"on": 1, "off": episodes}.items() if args.eval in (k, "both")}
    cases = [(v, e) for e in evals for v in variants]
    load_before = os.getloadavg()
    if not variants:  # --variants "" --profile: the profiles alone
        if not args.profile:
            parser.error("no variants and no --profile: nothing to do")
        with tempfile.TemporaryDirectory(prefix="bench-e2e-prof-") as tmp:
            profiles = run_profiles(tmp_config(Path(tmp)), args.profile_episodes, Path(tmp))
        out = {
            "command": command(__file__, argv),
            "config": CONFIG_YAML,
            "episodes": args.profile_episodes,
            "loadavg_before": load_before,
            "loadavg_after": os.getloadavg(),
            "profiles": profiles,
        }
        write_result(args.out, out, load_before)
        return
    runs: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench-e2e-") as tmp:
        tmp = Path(tmp)
        config = tmp_config(tmp)
        for r, (name, ev) in rotating_rounds(rounds, cases):
            work = tmp / f"r{r}-{name}-{ev}"
            load = begin_run(
                work, f"round {r + 1}/{rounds}: {name}, eval {ev}, {episodes} episodes"
            )
            before = floor_rates()
            res = run_variant(name, config, episodes, evals[ev], work)
            after = floor_rates()
            res.update(variant=name, eval=ev, round=r, loadavg_before=load)
            res["loadavg_after"] = os.getloadavg()
            res["floor_before"], res["floor_after"] = before, after
            probes = [p["2"] for p in (before, after) if p]
            res["floor2"] = statistics.mean(probes) if probes else None
            res["steady_over_floor2"] = (
                res["steady"]["rate"] / res["floor2"]
                if res["floor2"] and res["steady"]["rate"]
                else None
            )
            runs.append(res)
            progress(
                f"  steady {fmt(res['steady']['rate'])} steps/s, e2e "
                f"{fmt(res['e2e_steps_per_s'])} steps/s; floor on 2 threads "
                f"{fmt(res['floor2'])} updates/s around the run"
            )

    def get(r, name, ev):
        return next(
            (x for x in runs if x["round"] == r and x["variant"] == name and x["eval"] == ev), None
        )

    summary = []
    for ev in evals:
        for name in variants:
            rs = [get(r, name, ev) for r in range(rounds)]
            row = {
                "variant": name,
                "eval": ev,
                "steady_steps_per_s": median([x["steady"]["rate"] for x in rs]),
                "rows_steady_steps_per_s": median([x["rows_steady"] for x in rs]),
                "overall_steps_per_s": median([x["overall_steps_per_sec"] for x in rs]),
                "e2e_steps_per_s": median([x["e2e_steps_per_s"] for x in rs]),
                "samples_steady": [x["steady"]["rate"] for x in rs],
                "floor2": median([x["floor2"] for x in rs]),
                "steady_over_floor2": median([x["steady_over_floor2"] for x in rs]),
            }
            for base in BASELINES.get(name, ()):
                if base in variants:
                    ratios = [
                        x["steady"]["rate"] / get(x["round"], base, ev)["steady"]["rate"]
                        for x in rs
                    ]
                    e2e = [
                        x["e2e_steps_per_s"] / get(x["round"], base, ev)["e2e_steps_per_s"]
                        for x in rs
                    ]
                    row[f"over_{base}"] = median(ratios)
                    row[f"e2e_over_{base}"] = median(e2e)
            if name.startswith("cluster"):
                modes = sorted({k for x in rs for k in x["learner"] if k.endswith("_share")})
                row["learner_modes"] = {k: median([x["learner"].get(k) for x in rs]) for k in modes}
                row["learner_bonus_p50_ms"] = median([x["learner"]["bonus_p50_ms"] for x in rs])
                row["learner_bonus_p99_ms"] = median([x["learner"]["bonus_p99_ms"] for x in rs])
                row["learner_bonus_wait_ms_per_update"] = median(
                    [x["learner"].get("bonus_wait_ms_per_update") for x in rs]
                )
                row["replay_ratio"] = median([x["learner"]["replay_ratio"] for x in rs])
                row["evaluator_lag_s"] = median([x["evaluator_lag_s"] for x in rs])
                row["startup_s"] = median([x["startup_s"] for x in rs])
            roles = sorted({k for x in rs for k in x["cpu_share"]})
            row["cpu_share"] = {k: median([x["cpu_share"].get(k) for x in rs]) for k in roles}
            summary.append(row)

    print(
        f"\nspeaker_listener, Cen-MADDPG + Cen-MACB (k=512, beta=0.8, batch 100, hidden "
        f"400-300), {episodes} episodes, 1 actor; medians of {rounds} round(s)\n"
    )
    print(
        "| variant | eval | steady steps/s | from eval rows | overall (last row) "
        "| end-to-end steps/s | cluster / its trainer (steady; e2e) "
        "| cores used (steady window) | floor, 2 threads (updates/s) | steady / floor |"
    )
    print("|" + "---|" * 10)
    for s in summary:
        cpu = ", ".join(f"{k} {v:.2f}" for k, v in s["cpu_share"].items() if v and v >= 0.02)
        ratios = "; ".join(
            f"{ratio_pair(s, base)} vs {base}"
            for base in BASELINES.get(s["variant"], ())
            if f"over_{base}" in s
        )
        print(
            f"| {s['variant']} | {s['eval']} | {fmt(s['steady_steps_per_s'])} "
            f"| {fmt(s['rows_steady_steps_per_s'])} | {fmt(s['overall_steps_per_s'])} "
            f"| {fmt(s['e2e_steps_per_s'])} | {ratios} | {cpu} | {fmt(s['floor2'])} "
            f"| {fmt(s['steady_over_floor2'], '.3f')} |"
        )
    print(
        "\n'floor': the update's matrix products alone on two threads (bench_learner's "
        "floor), timed just before and after each run: the machine's speed for this "
        "workload then. 'steady / floor': env steps per floor update, the share of the "
        "machine's speed the run turned into steps (136 steps/s at session 3's floor of "
        "294/s would be 0.46)."
    )
    clusters = [s for s in summary if s["variant"].startswith("cluster")]
    for s in clusters:
        print(
            f"\n{s['variant']}, eval {s['eval']}: learner's bonus query (one a tick) "
            f"p50 {fmt(s['learner_bonus_p50_ms'], '.2f')} ms, p99 "
            f"{fmt(s['learner_bonus_p99_ms'], '.2f')} ms, waiting for bonuses "
            f"{fmt(s['learner_bonus_wait_ms_per_update'], '.2f')} ms per update; update "
            f"modes (share of updates, lanes x torch threads) {s['learner_modes'] or '-'}; "
            "replay ratio "
            f"{fmt(s['replay_ratio'], '.3f')}; evaluator finished "
            f"{fmt(s['evaluator_lag_s'], '.1f')} s after the learner; startup "
            f"{fmt(s['startup_s'], '.1f')} s"
        )
    targets = {}
    on = next((s for s in clusters if s["eval"] == "on" and s["variant"] == "cluster"), None)
    if on is not None:
        targets["cluster_eval_on_ge_136"] = {
            "target": TARGET_CLUSTER_EVAL_ON,
            "measured_steady": on["steady_steps_per_s"],
            "measured_e2e": on["e2e_steps_per_s"],
            "met": bool((on["steady_steps_per_s"] or 0) >= TARGET_CLUSTER_EVAL_ON),
        }
    for s in clusters:
        for base in BASELINES[s["variant"]]:
            if f"over_{base}" in s:
                targets[f"{s['variant']}_within_15pct_of_{base}_eval_{s['eval']}"] = {
                    "target_ratio": TARGET_RATIO,
                    "measured_ratio": s[f"over_{base}"],
                    "met": bool((s[f"over_{base}"] or 0) >= TARGET_RATIO),
                }
    print("\ntargets (thesis code: 34 steps/s with the bonus, 70 without):")
    if on is not None:
        targets["cluster_eval_on_ge_136"]["floor2"] = on["floor2"]
        targets["cluster_eval_on_ge_136"]["steady_over_floor2"] = on["steady_over_floor2"]
    for k, t in targets.items():
        got = t.get("measured_steady", t.get("measured_ratio"))
        want = t.get("target", t.get("target_ratio"))
        print(f"  {k}: {fmt(got, '.2f')} vs {want}: {'met' if t['met'] else 'NOT met'}")
    profiles = None
    if args.profile:
        with tempfile.TemporaryDirectory(prefix="bench-e2e-prof-") as tmp:
            profiles = run_profiles(tmp_config(Path(tmp)), args.profile_episodes, Path(tmp))
    result = {
        "command": command(__file__, argv),
        "config": CONFIG_YAML,
        "episodes": episodes,
        "rounds": rounds,
        "variants": variants,
        "cores": os.cpu_count(),
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
        "thesis_steps_per_s": THESIS_STEPS_PER_S,
        "summary": summary,
        "targets": targets,
        "profiles": profiles,
        "runs": runs,
    }
    write_result(args.out, result, load_before)


if __name__ == "__main__":
    main()
