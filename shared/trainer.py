"""The one-process trainer: the thesis's loop with the same cores the services use.

Per environment step: act with noise, store the transition, count it (collection is
the only place counts change), and, after `learning_starts` transitions, sample one
batch, price its bonus from the current counts and do one update. After every
`eval_every` training episodes, run `eval_episodes` noise-free episodes and write
one metrics row.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from shared.config import TrainConfig
from shared.exploration import BonusDiagnostics, CountExploration, constant_shift
from shared.factories import build_exploration, build_learner, minibatches_per_update
from shared.learners import Learner
from shared.metrics import TRAIN_FIELDS
from shared.replay import ReplayBuffer, update_arrays
from shared.rollout import derive_seed, evaluate, make_collector
from shared.tasks import make_task_for

log = logging.getLogger("macb.trainer")

METRIC_FIELDS = TRAIN_FIELDS


class MetricsWriter:
    """Appends rows to metrics.csv and metrics.jsonl as they are produced."""

    def __init__(self, out: Path, fields: tuple[str, ...] = METRIC_FIELDS) -> None:
        self.csv_file = (out / "metrics.csv").open("w", newline="")
        self.csv = csv.DictWriter(self.csv_file, fieldnames=fields, extrasaction="ignore")
        self.csv.writeheader()
        self.jsonl = (out / "metrics.jsonl").open("w")

    def write(self, row: dict) -> None:
        self.csv.writerow(row)
        self.jsonl.write(json.dumps(row) + "\n")
        self.csv_file.flush()
        self.jsonl.flush()

    def close(self) -> None:
        self.csv_file.close()
        self.jsonl.close()


def save_checkpoint(
    path: Path,
    learner: Learner,
    explorer: CountExploration,
    counters: dict,
    cfg: TrainConfig,
) -> None:
    """Networks, optimizers, step counters and count tables together, without pickle."""
    tables = {}
    for t, table in enumerate(explorer.tables):
        keys, counts = table.to_arrays()
        tables[f"table{t}"] = {
            "keys": torch.from_numpy(keys.copy()),
            "counts": torch.from_numpy(counts),
            "total": table.total,
        }
    state = {
        "config": json.dumps(cfg.model_dump(mode="json")),
        "learner": learner.state_dict(),
        "counters": counters,
        "tables": tables,
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def load_checkpoint(path: Path) -> dict:
    return torch.load(path, weights_only=True)


def _say_if_constant_shift(rows: list[dict], warned: bool) -> bool:
    """Log, once each time it starts, that the bonus has been a constant reward shift
    (every sampled key new, or the constant arm): then counting did nothing yet that a
    constant bonus would not do. Returns whether it holds now."""
    shift = constant_shift(rows)
    if shift and not warned:
        r = rows[-1]
        log.warning(
            "episode %d: the bonus is a constant shift (%.4g on every sampled row, "
            "sampled count-1 %.1f%%): counting has not changed any reward yet",
            r["episode"],
            r["bonus_mean"],
            r["sampled_count1_pct"],
        )
    return shift


def train(
    cfg: TrainConfig,
    out: Path | None,
    progress: bool = True,
    on_metrics: Callable[[dict], None] | None = None,
    stop_when: Callable[[dict], bool] | None = None,
) -> list[dict]:
    """Run one experiment; returns the metric rows (also written under `out`).

    `stop_when(row)` returning True ends the run early after that evaluation.

    numpy's BLAS (the SimHash projections) runs on one thread while it trains, as in
    `macb train` and the services, which set it before numpy loads: from Python, numpy
    is usually loaded already with a thread per core, and the k=512 projections of a
    100-row batch then kept a second core busy (1.03 cores for counting against 0.04,
    bench_scaling) beside torch's own threads. The caller's setting is restored after.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _train(cfg, out, progress, on_metrics, stop_when)


def _train(
    cfg: TrainConfig,
    out: Path | None,
    progress: bool,
    on_metrics: Callable[[dict], None] | None,
    stop_when: Callable[[dict], bool] | None,
) -> list[dict]:
    torch.set_num_threads(cfg.threads)
    env = make_task_for(cfg)
    spec = env.spec
    eval_envs = [make_task_for(cfg) for _ in range(min(cfg.eval_episodes, 10))]
    for j, e in enumerate(eval_envs):
        e.reset(seed=derive_seed(cfg.seed, "eval", j))
    learner = build_learner(cfg, spec)
    explorer = build_exploration(cfg, spec)
    buffer = ReplayBuffer(
        min(cfg.buffer_size, cfg.episodes * cfg.episode_len), spec.joint_obs_dim, spec.joint_act_dim
    )
    collector = make_collector(cfg, env)
    sample_rng = np.random.default_rng(derive_seed(cfg.seed, "sampler"))
    writer = None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=2) + "\n")
        writer = MetricsWriter(out)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.episodes, unit="ep", desc=f"{cfg.task} {cfg.algo}+{cfg.explore}")
    rows: list[dict] = []
    draws = minibatches_per_update(cfg)
    diagnostics = BonusDiagnostics()
    shift_warned = False
    env_steps = collisions_cum = 0
    eval_s = 0.0
    start = time.perf_counter()
    try:
        for episode in range(1, cfg.episodes + 1):
            for _ in range(cfg.episode_len):
                tr = collector.step(learner.act)
                buffer.add(tr.obs, tr.act, tr.rew, tr.next_obs, tr.done)
                explorer.observe(tr.obs[None], tr.act[None])
                env_steps += 1
                collisions_cum += tr.collisions
                if env_steps > cfg.learning_starts:
                    batches = [buffer.sample(cfg.batch_size, sample_rng) for _ in range(draws)]
                    bonuses = []
                    for b in batches:
                        counts = explorer.counts(b.obs, b.act)
                        bonuses.append(explorer.bonus_from_counts(counts, len(b.rew)))
                        diagnostics.record(bonuses[-1], counts)
                    learner.update(*update_arrays(batches, bonuses))
            if episode % cfg.eval_every == 0 or episode == cfg.episodes:
                t0 = time.perf_counter()
                ev = evaluate(learner.act, eval_envs, cfg.eval_episodes)
                eval_s += time.perf_counter() - t0
                wall = time.perf_counter() - start
                row = {
                    "episode": episode,
                    "env_steps": env_steps,
                    "success_rate": ev.success_rate,
                    "eval_return": ev.eval_return,
                    "collisions_cum": collisions_cum,
                    **explorer.stats(),
                    **diagnostics.take(),
                    "steps_per_sec": env_steps / wall,
                    "train_steps_per_sec": env_steps / max(wall - eval_s, 1e-9),
                    "updates": learner.updates,
                    "wall_s": wall,
                }
                rows.append(row)
                shift_warned = _say_if_constant_shift(rows, shift_warned)
                if writer:
                    writer.write(row)
                if on_metrics:
                    on_metrics(row)
                if bar:
                    bar.set_postfix(
                        success=f"{ev.success_rate:.2f}", sps=f"{row['steps_per_sec']:.0f}"
                    )
                if stop_when and stop_when(row):
                    break
            if bar:
                bar.update(1)
    finally:
        if bar:
            bar.close()
        if writer:
            writer.close()
    if out is not None:
        episodes = rows[-1]["episode"] if rows else 0
        counters = {"env_steps": env_steps, "episodes": episodes, "updates": learner.updates}
        save_checkpoint(out / "checkpoint.pt", learner, explorer, counters, cfg)
        log.info("wrote %s", out)
    return rows
