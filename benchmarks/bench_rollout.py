"""Collection and evaluation cost: what the actor and the evaluator spend per episode.

On 2 cores every millisecond the actor and the evaluator spend is taken from the
learner's two threads, so their cost per training episode bounds the cluster. This
times, per task (thesis settings: hidden 400-300, 20-step episodes):

* an evaluation point: `eval_episodes` (10) noise-free episodes in lockstep,
  `shared.run.rollout.evaluate`, as the evaluator runs it;
* an actor's training episode: 20 noisy steps of `shared.run.rollout.Collector`, as the
  actor runs it;

each in three ways, alternated in rounds in a rotating order:

* `platform`: the code as it runs (the joint step `TaskEnv.step_joint` driving mpe2
  directly, the numpy `JointPolicy`);
* `per_agent`: mpe2 driven directly too, but per-agent actions split from and
  observations joined into the joint vectors (`TaskEnv.step`), and the torch actor
  modules: what the joint step and the numpy policy save. (The platform before
  session 5 also computed mpe2's per-agent rewards every step, so it was slower than
  this: 19.4 ms per speaker_listener evaluation point in a side-by-side check.)
* `baseline`: the straightforward way: PettingZoo's public parallel API (`direct=False`:
  per-agent action dicts through the AEC layers) and the torch actor modules.

Ratios are medians of per-round ratios (other way / platform), so the machine's drift
between rounds cancels. Runs with one BLAS and torch thread, as the services do.

    .venv/bin/python benchmarks/bench_rollout.py [--quick] [--tasks speaker_listener,...]

prints a markdown table and writes benchmarks/results/rollout.json.
"""

# Imports below pin_threads(), which must set the thread variables before numpy loads:
# ruff: noqa: E402
from __future__ import annotations

import os
import sys

from _procs import pin_threads

pin_threads()  # as every service runs; before numpy is imported

import json
import statistics
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from _harness import add_out, bench_parser, progress
from _stats import measure as measure_rounds
from _stats import ratio_median

from shared.core.networks import JointPolicy
from shared.envs.tasks import TASKS, JointStep, TaskEnv, make_task
from shared.run.rollout import Collector, evaluate

HIDDEN = (400, 300)
EPISODE_LEN = 20
EVAL_EPISODES = 10
NOISE_SIGMA = 0.1


class TorchPolicy:
    """The baseline policy: each agent's torch actor module on its slice, joined."""

    def __init__(self, policy: JointPolicy) -> None:
        self.actors, self.bounds = policy.actors, policy.bounds

    @torch.no_grad()
    def __call__(self, obs: np.ndarray) -> np.ndarray:
        o, b = torch.as_tensor(obs, dtype=torch.float32), self.bounds
        parts = [actor(o[..., b[i] : b[i + 1]]) for i, actor in enumerate(self.actors)]
        return torch.cat(parts, -1).numpy()


class PerAgentEnv:
    """The baseline's env: the joint step through per-agent actions (`TaskEnv.step`),
    split from the joint action and joined back, so `Collector` and `evaluate` run
    unchanged on it."""

    def __init__(self, env: TaskEnv) -> None:
        self.env, self.spec = env, env.spec
        self.split = np.cumsum(env.spec.act_dims)[:-1]

    def reset(self, seed: int | None = None) -> list[np.ndarray]:
        return self.env.reset(seed)

    def step_joint(self, action: np.ndarray) -> JointStep:
        res = self.env.step(np.split(action, self.split))
        obs = np.concatenate(res.obs)
        return JointStep(obs, res.reward, res.success, res.collisions, res.truncated)


def _env(task: str, seed: int, direct: bool, per_agent: bool) -> TaskEnv | PerAgentEnv:
    env = make_task(task, 2, "sparse", EPISODE_LEN, seed=seed, direct=direct)
    return PerAgentEnv(env) if per_agent else env


def make_cases(task: str) -> dict[str, dict[str, Callable[[], None]]]:
    """{measure: {way: one timed call}}."""
    torch.manual_seed(0)
    spec = make_task(task).spec
    policy = JointPolicy(
        spec.obs_dims, [a.act_low for a in spec.agents], [a.act_high for a in spec.agents], HIDDEN
    )
    cases: dict[str, dict[str, Callable[[], None]]] = {"eval_point": {}, "actor_episode": {}}
    torch_policy = TorchPolicy(policy)
    for way, direct, pol, per_agent in (
        ("platform", True, policy, False),
        ("per_agent", True, torch_policy, True),
        ("baseline", False, torch_policy, True),
    ):
        envs = [_env(task, j, direct, per_agent) for j in range(EVAL_EPISODES)]
        cases["eval_point"][way] = lambda p=pol, e=envs: evaluate(p, e, EVAL_EPISODES)
        col = Collector(_env(task, 0, direct, per_agent), NOISE_SIGMA, seed=0)
        cases["actor_episode"][way] = lambda p=pol, c=col: [c.step(p) for _ in range(EPISODE_LEN)]
    return cases


def main() -> int:
    ap = bench_parser(__doc__, "rollout.json", prints="a markdown table")
    ap.add_argument("--quick", action="store_true", help="2 rounds of 0.3 s per case (~15 s)")
    ap.add_argument("--rounds", type=int, default=None, help="rounds (default 5; quick 2)")
    ap.add_argument("--tasks", default=",".join(TASKS), help=f"comma-separated of {TASKS}")
    add_out(ap, "rollout.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rounds = args.rounds or (2 if args.quick else 5)
    budget_s = 0.3 if args.quick else 1.0  # per case and round
    tasks = [t for t in args.tasks.split(",") if t]
    unknown = sorted(set(tasks) - set(TASKS))
    if unknown:
        ap.error(f"unknown task(s) {unknown}; expected some of {TASKS}")

    samples: dict[tuple[str, str, str], list[float]] = {}
    for task in tasks:
        progress(f"{task}: {rounds} rounds")
        cases = make_cases(task)
        fns = {(task, m, w): fn for m in cases for w, fn in cases[m].items()}
        samples.update(measure_rounds(fns, rounds, budget_s))

    rows = []
    for task in tasks:
        for measure in ("eval_point", "actor_episode"):
            ms = {w: samples[(task, measure, w)] for w in ("platform", "per_agent", "baseline")}
            row: dict[str, object] = {"task": task, "measure": measure}
            for way, xs in ms.items():
                row[f"{way}_ms"] = statistics.median(xs) * 1e3
                row[f"{way}_over_platform"] = ratio_median(xs, ms["platform"])
            rows.append(row)
    print(
        f"\nCollection and evaluation, hidden {HIDDEN[0]}-{HIDDEN[1]}, {EPISODE_LEN}-step "
        f"episodes, 1 thread; medians of {rounds} rounds\n"
    )
    print("| task | measure | platform ms | per_agent ms (x) | baseline ms (x) |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['task']} | {row['measure']} | {row['platform_ms']:.2f} "
            f"| {row['per_agent_ms']:.2f} ({row['per_agent_over_platform']:.2f}x) "
            f"| {row['baseline_ms']:.2f} ({row['baseline_over_platform']:.2f}x) |"
        )
    print(
        "\n'eval_point': 10 noise-free episodes in lockstep (the evaluator's work per "
        "training episode); 'actor_episode': one noisy training episode. 'per_agent': "
        "mpe2 stepped directly with per-agent actions and the torch actor modules; "
        "'baseline': PettingZoo's parallel API and the torch actor modules. (x): "
        "median of per-round ratios to 'platform'."
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "rounds": rounds,
        "loadavg": os.getloadavg(),
        "rows": rows,
        "samples_ms": {"/".join(k): [s * 1e3 for s in v] for k, v in samples.items()},
    }
    out.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
