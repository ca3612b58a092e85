"""Run groups: R runs of one task and network shape trained as one, in one process.

The thesis's loop (cli/trainer.py) for every run of the group at once: each step,
one policy call acts for every run (with the current weights), the R worlds step as
arrays (shared/envs/vectask.py), each run stores and counts its own transition (collection
is the only place counts change), samples its own minibatch, prices its bonus from its
own counts, and one `GroupMADDPG.update` updates every run. After every `eval_every`
episodes one batched rollout runs every run's noise-free evaluation episodes.

What stays per run is everything that makes it a run: its config (seed, exploration,
beta, k, reward, noise, ...), replay buffer, count tables, RNG streams, metrics, output
folder, cuts and provenance. Run r's rows are those `macb train` gives it alone (fp32,
`learner_lanes: 1`, timing columns aside; tests/test_group_trainer.py), and each run's
cut is a `macb train` cut: a group resumes from them, and so could the run alone.

Runs may be grouped when their update and their task's steps can be shared:
`shared.groups` says which runs may (`group_key`: the config without the fields a run
may choose for itself, `PER_RUN_FIELDS`).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from cli.trainer import (
    DEFAULT_CUT_EVERY_S,
    MetricsWriter,
    _say_if_constant_shift,
    append_pending,
    check_resumable,
    cut_counters,
    load_counters,
    metric_row,
    price_at_collection,
    price_batches,
    refill,
    save_checkpoint,
)
from shared.config import TrainConfig
from shared.core.exploration import BonusDiagnostics
from shared.core.learners.group import GroupMADDPG
from shared.core.replay import ReplayBuffer, update_arrays
from shared.envs.tasks import make_task_for, task_spec_for
from shared.envs.vectask import vectorize
from shared.groups import check_group
from shared.persist import provenance
from shared.persist.checkpoint import CutError, load_tables
from shared.persist.cuts import ReplayLog, latest_cut, read_cut, write_cut
from shared.persist.cuts import clear as clear_cuts
from shared.run.factories import (
    agent_dims,
    build_exploration,
    learner_spec,
    minibatches_per_update,
)
from shared.run.rollout import derive_seed, evaluate_group, make_vec_collector

log = logging.getLogger("macb.group")


class Member:
    """One run of a group: its own parts, counters, rows and files."""

    def __init__(self, cfg: TrainConfig, out: Path | None, spec) -> None:
        self.cfg, self.out = cfg, out
        self.explorer = build_exploration(cfg, spec)
        capacity = min(cfg.buffer_size, cfg.episodes * cfg.episode_len)
        self.collection = cfg.bonus_at == "collection"
        stored = spec.n_agents if self.collection else 0
        self.buffer = ReplayBuffer(capacity, spec.joint_obs_dim, spec.joint_act_dim, stored)
        self.sample_rng = np.random.default_rng(derive_seed(cfg.seed, "sampler"))
        self.diagnostics = BonusDiagnostics()
        self.rows: list[dict] = []
        self.shift_warned = False
        self.env_steps = self.collisions_cum = 0
        self.eval_s = self.wall_before = 0.0
        self.cuts = self.replay = None
        self.replay_rows = 0
        self.pending: list[tuple[np.ndarray, ...]] = []
        self.writer: MetricsWriter | None = None
        if out is not None:
            self.cuts = out / "cuts"
            self.replay = ReplayLog(self.cuts)


def train_group(
    cfgs: Sequence[TrainConfig],
    outs: Sequence[Path | None],
    progress: bool = True,
    on_metrics: Callable[[int, dict], None] | None = None,
    resume: bool = False,
    cut_every_s: float = DEFAULT_CUT_EVERY_S,
    desc: str | None = None,
    position: int | None = None,
) -> list[list[dict]]:
    """Train `cfgs` as one group; returns each run's metric rows (also written under
    its `outs` folder). `on_metrics(r, row)` sees run r's rows as they come. With
    `resume`, every run continues from its newest cut that all runs have (one episode),
    keeping its rows up to it."""
    if resume and any(o is None for o in outs):
        raise ValueError("resume needs every run's output folder")
    with threadpool_limits(limits=1, user_api="blas"):
        group = GroupRun(cfgs, outs, cut_every_s)
        if resume:
            group.restore()
        else:
            for m in group.members:
                if m.cuts is not None and m.cuts.exists():
                    clear_cuts(m.cuts)
        return group.go(progress, on_metrics, desc, position)


class GroupRun:
    """A group's shared parts (worlds, learner, collector) and its runs (`Member`s)."""

    def __init__(
        self, cfgs: Sequence[TrainConfig], outs: Sequence[Path | None], cut_every_s: float
    ) -> None:
        cfgs = list(cfgs)
        if len(outs) != len(cfgs):
            raise ValueError(f"{len(cfgs)} runs but {len(outs)} output folders")
        if len({o is None for o in outs}) > 1:
            raise ValueError("give every run of a group an output folder, or none")
        check_group(cfgs)
        c0 = self.cfg = cfgs[0]
        torch.set_num_threads(c0.threads)
        self.runs = len(cfgs)
        self.cut_every_s = cut_every_s
        self.spec = spec = task_spec_for(c0)
        self.members = [Member(cfg, out, spec) for cfg, out in zip(cfgs, outs)]
        self.venv = vectorize([make_task_for(cfg) for cfg in cfgs])
        m = min(c0.eval_episodes, 10)
        eval_envs = []
        for cfg in cfgs:
            for j in range(m):
                env = make_task_for(cfg)
                env.reset(seed=derive_seed(cfg.seed, "eval", j))
                eval_envs.append(env)
        self.eval_venv = vectorize(eval_envs)
        self.learner = GroupMADDPG(
            agent_dims(spec),
            [learner_spec(cfg) for cfg in cfgs],
            precision=c0.precision,
            device=c0.device,
        )
        self.collector = make_vec_collector(cfgs, self.venv)
        self.minibatches_per_update = minibatches_per_update(c0)
        self.first_episode = 1
        self.resumed = False
        self.width = {
            "obs": spec.joint_obs_dim,
            "act": spec.joint_act_dim,
            "rew": 1,
            "next_obs": spec.joint_obs_dim,
            "done": 1,
        }
        self.last_cut = time.monotonic()
        self.cut_log: list[tuple[int, float]] = []
        # Seconds spent acting and stepping the worlds, storing and counting, sampling
        # and pricing, updating, evaluating (what benchmarks/bench_group.py reports).
        self.timing = dict.fromkeys(
            ("act_env", "store_count", "sample_price", "update", "eval"), 0.0
        )

    # ------------------------------------------------------------------ the loop
    def go(
        self, progress: bool, on_metrics, desc: str | None = None, position: int | None = None
    ) -> list[list[dict]]:
        c0 = self.cfg
        stats = self.learner.stats()
        for m in self.members:
            if m.out is None:
                continue
            m.out.mkdir(parents=True, exist_ok=True)
            start = provenance.entry(m.cfg.precision, stats, "group")
            start["group"] = {"runs": self.runs}
            if self.resumed:
                provenance.append(m.out / provenance.FILE, start)
            else:
                provenance.write(m.out / provenance.FILE, [start])
            config = json.dumps(m.cfg.model_dump(mode="json"), indent=2) + "\n"
            (m.out / "config.json").write_text(config)
            m.writer = MetricsWriter(m.out, rows=m.rows)
        bar = None
        if progress:
            from tqdm import tqdm

            desc = desc or f"{self.runs} runs: {c0.task} {c0.algo}"
            bar = tqdm(
                total=c0.episodes,
                initial=self.first_episode - 1,
                unit="ep",
                desc=desc,
                position=position,
            )
        self.start = time.perf_counter()
        try:
            for episode in range(self.first_episode, c0.episodes + 1):
                self.episode()
                if episode % c0.eval_every == 0 or episode == c0.episodes:
                    rows = self.point(episode)
                    for r, (m, row) in enumerate(zip(self.members, rows)):
                        if m.writer:
                            m.writer.write(row)
                        if on_metrics:
                            on_metrics(r, row)
                    first = len(self.members[0].rows) == 1
                    if self.members[0].cuts is not None and (
                        first
                        or time.monotonic() - self.last_cut >= self.cut_every_s
                        or episode == c0.episodes
                    ):
                        self.cut(episode)
                    if bar:
                        mean = np.mean([row["success_rate"] for row in rows])
                        sps = sum(row["steps_per_sec"] for row in rows)
                        bar.set_postfix(success=f"{mean:.2f}", run_sps=f"{sps:.0f}")
                if bar:
                    bar.update(1)
        finally:
            if bar:
                bar.close()
            for m in self.members:
                if m.writer:
                    m.writer.close()
        for r, m in enumerate(self.members):
            if m.out is None:
                continue
            episodes = m.rows[-1]["episode"] if m.rows else 0
            counters = {
                "env_steps": m.env_steps,
                "episodes": episodes,
                "updates": self.learner.updates,
            }
            one = self.learner.run_learner(r)
            save_checkpoint(m.out / "checkpoint.pt", one, m.explorer, counters, m.cfg)
            log.info("wrote %s", m.out)
        return [m.rows for m in self.members]

    def episode(self) -> None:
        c0, members, timing = self.cfg, self.members, self.timing
        clock = time.perf_counter
        for _ in range(c0.episode_len):
            t0 = clock()
            tr = self.collector.step(self.learner.act)
            t1 = clock()
            timing["act_env"] += t1 - t0
            for r, m in enumerate(members):
                obs, act, next_obs = tr.obs[r], tr.act[r], tr.next_obs[r]
                rew, done = float(tr.rew[r]), float(tr.done[r])
                m.explorer.observe(obs[None], act[None])
                stored = price_at_collection(m.explorer, obs, act, m.diagnostics, m.collection)
                m.buffer.add(obs, act, rew, next_obs, done, stored)
                if m.replay is not None:
                    row = (obs, act, rew, next_obs, done)
                    m.pending.append(row if stored is None else (*row, stored))
                m.env_steps += 1
                m.collisions_cum += int(tr.collisions[r])
            t2 = clock()
            timing["store_count"] += t2 - t1
            if members[0].env_steps > c0.learning_starts:
                parts = []
                for m in members:
                    batches = [
                        m.buffer.sample(c0.batch_size, m.sample_rng)
                        for _ in range(self.minibatches_per_update)
                    ]
                    bonuses = price_batches(m.explorer, batches, m.diagnostics)
                    parts.append(update_arrays(batches, bonuses))
                arrays = [np.stack(cols) for cols in zip(*parts)]
                t3 = clock()
                self.learner.update(*arrays)
                timing["sample_price"] += t3 - t2
                timing["update"] += clock() - t3

    def point(self, episode: int) -> list[dict]:
        t0 = time.perf_counter()
        results = evaluate_group(
            self.learner.act, self.eval_venv, self.runs, self.cfg.eval_episodes
        )
        spent = time.perf_counter() - t0
        self.timing["eval"] += spent
        rows = []
        for m, ev in zip(self.members, results):
            m.eval_s += spent
            wall = m.wall_before + time.perf_counter() - self.start
            row = metric_row(episode, ev, m, self.learner.updates, wall)
            m.rows.append(row)
            m.shift_warned = _say_if_constant_shift(m.rows, m.shift_warned, m.explorer.counting)
            rows.append(row)
        return rows

    # ------------------------------------------------------------------ cuts
    def width_of(self, m: Member) -> dict[str, int]:
        """Run m's replay log columns (its stored bonus too, where it stores one)."""
        if m.collection:
            return {**self.width, "bonus": self.spec.n_agents}
        return self.width

    def cut(self, episode: int) -> None:
        """Each run's cut, in `macb train`'s format (its replay rows appended first)."""
        t0 = time.perf_counter()
        m_eval = min(self.cfg.eval_episodes, 10)
        for r, m in enumerate(self.members):
            assert m.cuts is not None and m.replay is not None
            append_pending(m, self.width_of(m))
            rng = {
                "collector": self.collector.state(r),
                "sampler": dict(m.sample_rng.bit_generator.state),
                "eval_envs": [self.eval_venv.rng_state(r * m_eval + j) for j in range(m_eval)],
            }
            wall = m.wall_before + time.perf_counter() - self.start
            write_cut(
                m.cuts,
                episode,
                config=m.cfg.model_dump(mode="json"),
                learner=self.learner.run_state_dict(r),
                counters=cut_counters(m, wall),
                rng=rng,
                tables=m.explorer.tables,
                replay_rows=m.replay_rows,
                torch_rng=torch.get_rng_state(),
            )
        self.last_cut = time.monotonic()
        self.cut_log.append((episode, time.perf_counter() - t0))

    def restore(self) -> None:
        """Continue every run from its cut at the newest episode all runs have a cut of."""
        cuts = []
        for m in self.members:
            assert m.out is not None and m.cuts is not None
            config = m.cfg.model_dump(mode="json")
            check_resumable(m.out, config)
            cuts.append(latest_cut(m.cuts, config))
        episode = min(c.episode for c in cuts)
        for i, (m, c) in enumerate(zip(self.members, cuts)):
            if c.episode != episode:  # a group stopped while writing its runs' cuts
                path = m.cuts / f"cut-{episode:09d}.pt"
                if not path.exists():
                    raise CutError(f"{m.cuts}: no cut at episode {episode}, where the others are")
                cuts[i] = read_cut(path, m.cfg.model_dump(mode="json"))
        try:
            self.learner.load_run_state_dicts([c.state["learner"] for c in cuts])
        except (ValueError, KeyError, RuntimeError) as err:
            raise CutError(f"{cuts[0].path}: learner states do not fit: {err}") from None
        rngs = [c.state["rng"] for c in cuts]
        self.collector.load_state([rng["collector"] for rng in rngs])
        m_eval = min(self.cfg.eval_episodes, 10)
        for r, (m, cut, rng) in enumerate(zip(self.members, cuts, rngs)):
            st = cut.state
            load_tables(m.explorer.tables, st["tables"], cut.path)
            refill(m, int(st["replay_rows"]), self.width_of(m), cut.path)
            m.sample_rng.bit_generator.state = rng["sampler"]
            for j, state in enumerate(rng["eval_envs"]):
                self.eval_venv.set_rng_state(r * m_eval + j, state)
            load_counters(m, st["counters"], m.out, cut.path)
        torch.set_rng_state(cuts[0].state["torch_rng"])
        self.resumed = True
        self.first_episode = episode + 1
        log.info(
            "resuming a group of %d runs from episode %d (%d updates)",
            self.runs,
            episode,
            self.learner.updates,
        )
