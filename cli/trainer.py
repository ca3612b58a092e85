"""The one-process trainer: the thesis's loop for R >= 1 runs, with the same cores the
services use. A run alone is a group of one: one loop, one cut and one restore.

Per environment step: one policy call acts (with noise) for every run, the R worlds step
as arrays (shared/envs/vectask.py; a custom task's world by world), each run stores and
counts its own transition (collection is the only place counts change; the row keeps its
slot in each of the run's tables), and, after `learning_starts` transitions, draws its
own minibatch's rows, prices their bonus from its own counts now at their slots, and one
gather over the group's replay and one learner update serve every run. After every
`eval_every` training episodes one batched rollout runs every run's `eval_episodes`
noise-free episodes and each run writes one metrics row.

What stays per run (`Member`) is everything that makes it a run: its config (seed,
exploration, beta, k, reward, noise, ...), replay buffer, count tables, RNG streams,
metrics, output folder, cuts and provenance. The learner is R runs' (`RunsLearner`): a
run alone keeps the one its config asks for (`build_learner`: the reference, the
batched one with its lanes, or the tuned one), R >= 2 runs share one `GroupMADDPG`, and
run r's rows are those it gives alone (fp32, `learner_lanes: 1`, timing columns aside;
tests/test_group_trainer.py). Each run's cut is a one-run cut: a group resumes from
them, and so could each run alone. Runs may be grouped when their update and their
task's steps can be shared (`shared.groups`).
"""

from __future__ import annotations

import csv
import json
import logging
import os
import resource
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from shared.config import TrainConfig
from shared.core.exploration import BonusDiagnostics, CountExploration, constant_shift
from shared.core.learners import Learner, RunsLearner, SoloRuns
from shared.core.learners.group import GroupMADDPG
from shared.core.learners.precision import resolve_device
from shared.core.replay import GroupReplay, ReplayBuffer, fixed_draws
from shared.core.transfer import send
from shared.envs.tasks import TaskSpec, make_task_for
from shared.envs.vectask import vectorize
from shared.groups import check_group
from shared.metrics import TRAIN_FIELDS, early_stop_reason, run_fields
from shared.persist import checkpoint, provenance, runlock
from shared.persist.checkpoint import CutError, folder_config_difference, load_tables
from shared.persist.cuts import ReplayLog, latest_cut, read_cut, write_cut
from shared.persist.cuts import clear as clear_cuts
from shared.persist.files import atomic_write
from shared.run.factories import (
    agent_dims,
    build_exploration,
    build_learner,
    learner_spec,
    minibatches_per_update,
)
from shared.run.heap import steady_heap
from shared.run.rollout import (
    EvalResult,
    WorldError,
    derive_seed,
    evaluate_group,
    make_vec_collector,
    nonfinite,
)
from shared.settings import settings

log = logging.getLogger("macb.trainer")

# A cut at the first evaluation point after this many seconds since the last one (and at
# the end): at ~150 env steps/s that is every ~9,000 transitions, whose replay rows and
# the learner's state are what a cut writes (docs/reliability.md).
DEFAULT_CUT_EVERY_S = 60.0

METRIC_FIELDS = TRAIN_FIELDS

# A cut waits at least this many times the recent cuts' seconds after the last, beyond
# the cut interval: late in a long run the count tables make a cut take seconds, and cuts
# then take at most about 1/CUT_SPACING of the loop's time. The least of the last
# CUT_SPACING_OVER cuts counts, so one cut slowed by a load beside the run does not space
# out the rest; and cuts are never more than CUT_MAX_WAIT_S apart (unless --cut-every
# asks for more), so a stop loses at most that much running.
CUT_SPACING = 50.0
CUT_SPACING_OVER = 3
CUT_MAX_WAIT_S = 900.0

# What GroupRun.timing sums, in seconds (the rest of a group's wall time is its loop's own).
TIMING_KEYS = ("act_env", "store_count", "sample", "price", "update", "eval", "rows", "cut")


class MetricsWriter:
    """Appends rows to metrics.csv and metrics.jsonl as they are produced; `rows` (a
    resumed run's rows up to its cut) are written first, replacing what was there."""

    def __init__(
        self, out: Path, fields: tuple[str, ...] = METRIC_FIELDS, rows: Sequence[dict] = ()
    ) -> None:
        self.csv_file = (out / "metrics.csv").open("w", newline="")
        self.csv = csv.DictWriter(self.csv_file, fieldnames=fields, extrasaction="ignore")
        self.csv.writeheader()
        self.jsonl = (out / "metrics.jsonl").open("w")
        for row in rows:
            self.csv.writerow(row)
            self.jsonl.write(json.dumps(row) + "\n")

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
    """Networks, optimizers, step counters and count tables together, without pickle:
    a learner checkpoint of kind `final` (shared/persist/checkpoint.py)."""
    config = cfg.model_dump(mode="json")
    checkpoint.save(path, "final", config, learner.state_dict(), counters, tables=explorer.tables)


def load_checkpoint(path: Path) -> dict:
    """A run's final checkpoint.pt (torch.load with weights_only=True inside): the
    trainer's, or the learner service's that `macb start --out` copies beside its rows."""
    return checkpoint.load(path, ("final", "service"))


def _say_if_constant_shift(rows: list[dict], warned: bool, counting: bool = True) -> bool:
    """Log, once each time it starts, that the bonus has been a constant reward shift:
    for a counting arm (every sampled key new) a warning, counting did nothing yet that a
    constant bonus would not do; for the constant arm, which counts nothing, a note that
    this is its design. Returns whether it holds now."""
    shift = constant_shift(rows)
    if shift and not warned:
        r = rows[-1]
        if not counting:
            log.info(
                "episode %d: the bonus is a constant shift by design (%.4g on every "
                "reward): the constant arm counts nothing",
                r["episode"],
                r["bonus_mean"],
            )
            return shift
        log.warning(
            "episode %d: the bonus is a constant shift (%.4g on every sampled row, "
            "sampled count-1 %.1f%%): counting has not changed any reward yet",
            r["episode"],
            r["bonus_mean"],
            r["sampled_count1_pct"],
        )
    return shift


def metric_row(episode: int, ev: EvalResult, run: Member, updates: int, wall: float) -> dict:
    """One evaluation point's row: `run`'s counters (`env_steps`, `collisions_cum`,
    `eval_s`), exploration stats and bonus diagnostics."""
    return {
        "episode": episode,
        "env_steps": run.env_steps,
        "success_rate": ev.success_rate,
        "eval_return": ev.eval_return,
        "collisions_cum": run.collisions_cum,
        **run.explorer.stats(),
        **run.diagnostics.take(),
        "steps_per_sec": run.env_steps / wall,
        "train_steps_per_sec": run.env_steps / max(wall - run.eval_s, 1e-9),
        "updates": updates,
        "wall_s": wall,
        **option_columns(run.cfg, run.env_steps),
    }


def option_columns(cfg: TrainConfig, env_steps: int) -> dict:
    """The row's columns of the options the run sets (shared.metrics.OPTION_FIELDS):
    the beta in force at its last transition, and `stop_reason` (set where the rule
    ends the run)."""
    out: dict = {}
    if cfg.beta_schedule is not None:
        out["beta"] = cfg.beta_at(env_steps)
    if cfg.early_stop is not None:
        out["stop_reason"] = None
    return out


def price_at_collection(
    explorer: CountExploration,
    slots: list[np.ndarray],
    diagnostics: BonusDiagnostics,
    on: bool,
    beta: float | None = None,
) -> np.ndarray | None:
    """`bonus_at: collection`: the just-counted transition's per-agent bonus (N,), from
    its count including itself (at its `slots`, what counting it returned), at `beta`
    (the schedule's now; None: the config's), to store with it (the diagnostics then
    describe the collected transitions); None when bonuses are priced at sample time."""
    if not on:
        return None
    counts = explorer.counts_at(slots)
    bonus = explorer.bonus_from_counts(counts, 1, beta)
    diagnostics.record(bonus, counts)
    return bonus[0]


def price_rows(
    explorer: CountExploration,
    slots: Sequence[np.ndarray],
    shape: tuple[int, int],
    diagnostics: BonusDiagnostics,
    beta: float | None = None,
) -> np.ndarray:
    """`shape` (k, B) sampled minibatches' per-agent bonuses (k, B, N), priced now from
    the current counts at the rows' `slots` (each table's (k, B, ...): a gather, the
    counts of the rows' keys without hashing them again; none for an arm that counts
    nothing) at `beta` (the schedule's now; None: the config's), each minibatch
    recorded in the diagnostics in turn."""
    counts = explorer.counts_at(slots)
    k, batch = shape
    out = np.empty((k, batch, explorer.n_agents), np.float32)
    for j in range(k):
        mine = [c[j] for c in counts]
        out[j] = explorer.bonus_from_counts(mine, batch, beta)
        diagnostics.record(out[j], mine)
    return out


def train(
    cfg: TrainConfig,
    out: Path | None,
    progress: bool = True,
    on_metrics: Callable[[dict], None] | None = None,
    stop_when: Callable[[dict], bool] | None = None,
    resume: bool = False,
    cut_every_s: float = DEFAULT_CUT_EVERY_S,
) -> list[dict]:
    """Run one experiment; returns the metric rows (also written under `out`): a group of
    one run (`train_group`), whose learner is the one its config asks for.

    `stop_when(row)` returning True ends the run early after that evaluation. With
    `out`, a cut (shared/persist/cuts.py) is written at an evaluation point whenever
    `cut_every_s` seconds have passed since the last one, and at the end; `resume`
    continues from the newest usable cut in `out` (its config.json must equal `cfg`),
    keeping the rows written up to it, so the rows come out as without the stop."""
    if resume and out is None:
        raise ValueError("resume needs the run's output folder")
    rows = train_group(
        [cfg],
        [out],
        progress,
        on_metrics=None if on_metrics is None else lambda r, row: on_metrics(row),
        resume=resume,
        cut_every_s=cut_every_s,
        stop_when=None if stop_when is None else lambda rows: stop_when(rows[0]),
        own_learner=True,
    )
    return rows[0]


def train_group(
    cfgs: Sequence[TrainConfig],
    outs: Sequence[Path | None],
    progress: bool = True,
    on_metrics: Callable[[int, dict], None] | None = None,
    resume: bool = False,
    cut_every_s: float = DEFAULT_CUT_EVERY_S,
    desc: str | None = None,
    position: int | None = None,
    stop_when: Callable[[list[dict]], bool] | None = None,
    own_learner: bool = False,
    command: str | None = None,
) -> list[list[dict]]:
    """Train `cfgs` as one group; returns each run's metric rows (also written under
    its `outs` folder). The runs share one `GroupMADDPG`, a group of one too: with
    `learner_lanes: auto` a run's own learner picks its lanes by timing, so a resumed
    run would not give its uninterrupted rows bit for bit. `own_learner` (`train`,
    one run) keeps the learner its config asks for instead.

    `command` names the command this start is part of, in each run's provenance (the
    page counts a command's starts as one restart). `on_metrics(r, row)` sees run r's
    rows as they come (after the point's cut);
    `stop_when(rows)` returning True ends every run after that point. With `resume`,
    every run continues from its newest cut that all runs have (one episode), keeping
    its rows up to it. Each run's folder is locked while it trains (`runlock.hold`):
    another process training it already is named in the `RunLocked` raised.

    numpy's BLAS (the SimHash projections) runs on one thread while it trains, as in
    `macb train` and the services, which set it before numpy loads: from Python, numpy
    is usually loaded already with a thread per core, and the k=512 projections of a
    100-row batch then kept a second core busy beside torch's own threads
    (bench_scaling). The caller's setting is restored after. The process's C heap keeps
    the update's temporaries' pages (`steady_heap`), so they do not fault anew each step."""
    if resume and any(o is None for o in outs):
        raise ValueError("resume needs every run's output folder")
    steady_heap()
    # One writer per run folder, before anything in it is read or written: a second
    # process is refused (runlock.RunLocked) having touched nothing.
    with (
        runlock.hold([o for o in outs if o is not None]),
        threadpool_limits(limits=1, user_api="blas"),
    ):
        group = GroupRun(cfgs, outs, cut_every_s, own_learner)
        group.command = command
        if resume:
            group.restore()
        else:
            for m in group.members:
                if m.cuts is not None and m.cuts.exists():
                    clear_cuts(m.cuts)  # a fresh run: an earlier run's cuts are not its own
        return group.go(progress, on_metrics, stop_when, desc, position)


class Member:
    """One run of a group: its own parts (count tables, replay buffer, sampler),
    counters, rows and files, and its cut's share of what it writes and reads back.
    Its replay buffer is its rows of the group's (`GroupReplay`), given by the group."""

    def __init__(self, cfg: TrainConfig, out: Path | None, spec: TaskSpec) -> None:
        self.cfg, self.out = cfg, out
        self.explorer = build_exploration(cfg, spec)
        self.capacity = min(cfg.buffer_size, cfg.episodes * cfg.episode_len)
        # bonus_at collection: priced once, when collected, and stored with the reward
        self.collection = cfg.bonus_at == "collection"
        self.stored = spec.n_agents if self.collection else 0
        self.buffer: ReplayBuffer  # (GroupRun sets it)
        self.sample_rng = np.random.default_rng(derive_seed(cfg.seed, "sampler"))
        self.diagnostics = BonusDiagnostics()
        self.rows: list[dict] = []
        self.shift_warned = False
        self.env_steps = self.collisions_cum = 0
        self.eval_s = self.wall_before = 0.0  # time spent in earlier lives of the run
        # The replay log's columns (the stored bonus too, where the run stores one).
        self.width = {"obs": spec.joint_obs_dim, "act": spec.joint_act_dim, "rew": 1}
        self.width |= {"next_obs": spec.joint_obs_dim, "done": 1}
        if self.collection:
            self.width["bonus"] = spec.n_agents
        self.cuts: Path | None = None
        self.replay: ReplayLog | None = None
        self.replay_rows = 0  # rows of the replay log on disk, as of the last cut
        # Every transition collected, kept since the last cut for the replay log.
        self.pending: list[tuple[Any, ...]] = []
        self.writer: MetricsWriter | None = None
        # early_stop: the episode and reason it stopped at (its rows end there, its world
        # steps on in the group, unread), the fixed minibatch its update entry runs on
        # after, the best success so far.
        self.stopped: tuple[int, str] | None = None
        self.frozen_draws: np.ndarray | None = None  # (its fixed draw's rows, once stopped)
        self.best = -1.0
        if out is not None:
            self.cuts = out / "cuts"
            self.replay = ReplayLog(self.cuts)

    def collect(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: float,
        next_obs: np.ndarray,
        done: float,
        collisions: int,
    ) -> None:
        """Count one transition of this run's, store it with its slot in each table
        (and its bonus when priced at collection) and keep it for the replay log. The
        key counted is the stored row's (float32, as every task gives), so the slot is
        the one its key at sample time has."""
        obs, act = np.asarray(obs, np.float32), np.asarray(act, np.float32)
        slots = self.explorer.observe(obs[None], act[None])
        beta = self.cfg.beta_at(self.env_steps + 1)  # this transition's
        stored = price_at_collection(self.explorer, slots, self.diagnostics, self.collection, beta)
        self.buffer.add(obs, act, rew, next_obs, done, stored, slots)
        if self.replay is not None:
            row = (obs, act, rew, next_obs, done)
            self.pending.append(row if stored is None else (*row, stored))
        self.env_steps += 1
        self.collisions_cum += collisions

    def price(self, idx: np.ndarray) -> np.ndarray | None:
        """The bonuses (k, B, N) of its sampled rows `idx` (k, B), from this run's counts
        now at the beta of its last transition (the update it owes; `beta_schedule`),
        recorded in its diagnostics; None where they were stored at collection."""
        if self.collection:
            return None
        beta = self.cfg.beta_at(self.env_steps)
        slots = [s[idx] for s in self.buffer.slots]
        return price_rows(self.explorer, slots, idx.shape, self.diagnostics, beta)

    def append_pending(self) -> int:
        """The transitions collected since the last cut, onto the replay log; bytes."""
        assert self.replay is not None
        if not self.pending:
            return 0
        cols = list(zip(*self.pending))
        arrays = {
            "obs": np.stack(cols[0]),
            "act": np.stack(cols[1]),
            "rew": np.asarray(cols[2], np.float32),
            "next_obs": np.stack(cols[3]),
            "done": np.asarray(cols[4], np.float32),
        }
        if self.collection:
            arrays["bonus"] = np.stack(cols[5])
        written = self.replay.append(arrays, self.replay_rows, self.width)
        self.replay_rows += len(self.pending)
        self.pending = []
        return written

    def refill(self, replay_rows: int, where: Path) -> None:
        """The replay buffer as it was at the cut: the log's last `capacity` rows, each
        at the slot it had (row r at r % capacity), so sampling goes on as without the
        stop."""
        assert self.replay is not None
        self.replay_rows = replay_rows
        data = self.replay.read(replay_rows, self.width, where)
        buffer = self.buffer
        first = replay_rows - min(replay_rows, buffer.capacity)
        buffer.added = first
        buffer.pos = first % buffer.capacity
        obs, act, rew, next_obs, done = (
            data[k][first:] for k in ("obs", "act", "rew", "next_obs", "done")
        )
        slots = self.slots_of(obs, act)
        buffer.add(
            obs, act, rew, next_obs, done, data["bonus"][first:] if self.collection else None,
            slots,
        )  # fmt: skip

    def slots_of(self, obs: np.ndarray, act: np.ndarray, chunk: int = 8192) -> list[np.ndarray]:
        """Each table's slots of stored rows, counting nothing: what counting them gave
        (a key's slot never changes). In chunks: a k-bit SimHash projects every row in
        float64, k values a row."""
        parts = [self.explorer.slots(obs[i : i + chunk], act[i : i + chunk])
                 for i in range(0, len(obs), chunk)]  # fmt: skip
        shapes = self.explorer.slot_shapes
        return [
            np.concatenate([p[t] for p in parts]) if parts else np.zeros((0, *shape), np.int32)
            for t, shape in enumerate(shapes)
        ]

    def counters(self, wall: float) -> dict:
        return {
            "env_steps": self.env_steps,
            "collisions_cum": self.collisions_cum,
            "rows": len(self.rows),
            "shift_warned": self.shift_warned,
            "eval_s": self.eval_s,
            "wall_s": wall,
        }

    def load_counters(self, c: dict, where: Path) -> None:
        """`counters` back, and the metric rows written up to the cut."""
        assert self.out is not None
        self.env_steps, self.collisions_cum = int(c["env_steps"]), int(c["collisions_cum"])
        self.shift_warned = bool(c["shift_warned"])
        self.eval_s, self.wall_before = float(c["eval_s"]), float(c["wall_s"])
        self.rows = _read_rows(self.out / "metrics.jsonl", int(c["rows"]), where)


class GroupRun:
    """R >= 1 runs' shared parts (worlds, learner, collector), their `Member`s and the
    one loop, cut and restore. The runs share one `GroupMADDPG`; with `own_learner` a
    run alone keeps the learner its config builds (`SoloRuns` around it: `macb train`)."""

    def __init__(
        self,
        cfgs: Sequence[TrainConfig],
        outs: Sequence[Path | None],
        cut_every_s: float,
        own_learner: bool = False,
        replay_backend: str | None = None,
    ) -> None:
        cfgs = list(cfgs)
        if len(outs) != len(cfgs):
            raise ValueError(f"{len(cfgs)} runs but {len(outs)} output folders")
        if len({o is None for o in outs}) > 1:
            raise ValueError("give every run of a group an output folder, or none")
        # A run alone keeps its config's learner when asked (`macb train`) or when it is
        # the reference one, which no group updates with (`form_groups` puts it alone).
        self.own = own = len(cfgs) == 1 and (own_learner or cfgs[0].learner_impl == "reference")
        if not own:
            check_group(cfgs)
        c0 = self.cfg = cfgs[0]
        torch.set_num_threads(c0.threads)
        self.runs = len(cfgs)
        self.cut_every_s = cut_every_s
        self.venv = vectorize([make_task_for(cfg) for cfg in cfgs])
        self.spec = spec = self.venv.spec
        self.members = members = [Member(cfg, out, spec) for cfg, out in zip(cfgs, outs)]
        self.names = [o.name if o is not None else f"{r}" for r, o in enumerate(outs)]
        self.replay = GroupReplay(
            [m.capacity for m in members],
            spec.joint_obs_dim,
            spec.joint_act_dim,
            [m.stored for m in members],
            [m.explorer.slot_shapes for m in members],
            device=resolve_device(c0.device),
            backend=replay_backend,
        )
        for member, buffer in zip(members, self.replay.buffers):
            member.buffer = buffer
        self.m_eval = m = min(c0.eval_episodes, 10)  # evaluation worlds per run
        eval_envs = []
        for cfg in cfgs:
            for j in range(m):
                env = make_task_for(cfg)
                env.reset(seed=derive_seed(cfg.seed, "eval", j))
                eval_envs.append(env)
        self.eval_venv = vectorize(eval_envs)
        self.learner: RunsLearner
        if own:
            self.learner = SoloRuns(build_learner(c0, spec))
        else:
            specs = [learner_spec(cfg) for cfg in cfgs]
            dims = agent_dims(spec)
            self.learner = GroupMADDPG(dims, specs, precision=c0.precision, device=c0.device)
        self.collector = make_vec_collector(cfgs, self.venv)
        self.minibatches_per_update = minibatches_per_update(c0)
        self.first_episode = 1
        self.resumed = False
        self.command: str | None = None  # the command whose start this is (provenance)
        self.last_cut = time.monotonic()
        # (episode, seconds, replay bytes appended, cut file bytes) of each cut written,
        # summed over the runs.
        self.cut_log: list[tuple[int, float, int, int]] = []
        # Seconds spent acting and stepping the worlds, storing and counting, sampling,
        # pricing, updating, evaluating, writing rows and cuts (what
        # benchmarks/bench_group.py and bench_fig8.py report).
        self.timing = dict.fromkeys(TIMING_KEYS, 0.0)
        # With MACB_GROUP_TIMING=DIR, `timing` at every point, written there at the end.
        self.timing_dir = settings().group_timing
        self.timing_log: list[dict[str, float]] = []

    # ------------------------------------------------------------------ the loop
    def go(
        self,
        progress: bool,
        on_metrics: Callable[[int, dict], None] | None,
        stop_when: Callable[[list[dict]], bool] | None = None,
        desc: str | None = None,
        position: int | None = None,
    ) -> list[list[dict]]:
        c0 = self.cfg
        self.start_files()
        bar = None
        if progress:
            from tqdm import tqdm

            alone = f"{c0.task} {c0.algo}+{c0.explore}"
            desc = desc or (alone if self.runs == 1 else f"{self.runs} runs: {c0.task} {c0.algo}")
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
                    points = self.point(episode)
                    stopping = self.early_stops(points)
                    t0 = time.perf_counter()
                    for m, row in zip(self.members, points):
                        if m.writer and row is not None:
                            m.writer.write(row)
                    self.timing["rows"] += time.perf_counter() - t0
                    if self.timing_dir:  # before the cut: a window's last cut is its next's
                        self.timing_log.append(self.timing_snapshot(episode))
                    for r in stopping:  # (its checkpoint before its cut: a resume from
                        self.stop_member(r)  # an earlier cut stops it here again)
                    if self.members[0].cuts is not None and (
                        max(len(m.rows) for m in self.members) == 1  # killed in its first minute
                        or self.cut_due()
                        or episode == c0.episodes
                        or stopping
                    ):
                        self.cut(episode)  # timed in `cut`
                    rows = [row for row in points if row is not None]
                    t0 = time.perf_counter()
                    for r, row in enumerate(points):
                        if on_metrics and row is not None:
                            on_metrics(r, row)
                    if bar and rows:
                        mean = np.mean([row["success_rate"] for row in rows])
                        sps = sum(row["steps_per_sec"] for row in rows)
                        bar.set_postfix(success=f"{mean:.2f}", sps=f"{sps:.0f}")
                    self.timing["rows"] += time.perf_counter() - t0
                    if stop_when and rows and stop_when(rows):
                        break
                    if all(m.stopped is not None for m in self.members):
                        break  # every run ended by its early_stop rule
                if bar:
                    bar.update(1)
        finally:
            if bar:
                bar.close()
            for m in self.members:
                if m.writer:
                    m.writer.close()
            if self.timing_dir:
                self.write_timing(Path(self.timing_dir))
        for r, m in enumerate(self.members):
            if m.stopped is None:
                self.final_checkpoint(r)
        return [m.rows for m in self.members]

    def final_checkpoint(self, r: int) -> None:
        """Run r's checkpoint.pt: its learner, counters and count tables now (a run
        stopped by its rule: as it stopped)."""
        m = self.members[r]
        if m.out is None:
            return
        episodes = m.rows[-1]["episode"] if m.rows else 0
        counters = {
            "env_steps": m.env_steps,
            "episodes": episodes,
            "updates": self.learner.updates,
        }
        one = self.learner.run_learner(r)
        save_checkpoint(m.out / "checkpoint.pt", one, m.explorer, counters, m.cfg)
        log.info("wrote %s", m.out)

    # ------------------------------------------------------------------ early stopping
    def early_stops(self, points: list[dict | None]) -> list[int]:
        """The runs whose `early_stop` rule holds at this point (their row gets the
        reason); each run's best point so far goes to its best.pt first."""
        stopping = []
        for r, (m, row) in enumerate(zip(self.members, points)):
            rule = m.cfg.early_stop
            if rule is None or row is None:
                continue
            if row["success_rate"] > m.best:  # the earliest of equal points is kept
                m.best = float(row["success_rate"])
                if m.out is not None:
                    state = self.learner.run_state_dict(r)
                    config = m.cfg.model_dump(mode="json")
                    checkpoint.save_best(m.out / checkpoint.BEST, config, state, row)
            if (why := early_stop_reason(rule, m.rows)) is not None:
                row["stop_reason"] = why
                stopping.append(r)
        return stopping

    def stop_member(self, r: int) -> None:
        """Run r ends here, completed by its rule: its checkpoint.pt now. In a group the
        others go on: its world still steps and its update entry still runs (on one
        fixed minibatch of its own, so the shared update keeps its shape and its cuts
        the group's update count), but nothing of it is counted, stored, priced or
        written again but its cuts, and the stack entries do not mix, so the others'
        rows are what they give alone."""
        m = self.members[r]
        episode = int(m.rows[-1]["episode"])
        m.stopped = (episode, str(m.rows[-1]["stop_reason"]))
        self.final_checkpoint(r)
        log.info("run %s: %s, at episode %d", m.out or r, m.stopped[1], episode)

    def update_arrays(
        self, idx: np.ndarray, bonuses: list[np.ndarray | None], live: list[bool]
    ) -> list[Any]:
        """The group update's (obs, act, rew, next_obs, done), each (R, ...): every run's
        rows `idx` (R, k, B) in one gather per field, rew plus each run's bonus (priced
        now, or stored at collection), and a stopped run's fixed draw (`fixed_draws`)
        with no bonus in its place: each run's entry what `update_arrays` of its
        minibatches gives (a stopped run's, what `fixed_update_arrays` gives). With the
        replay on a device (`GroupReplay`'s torch backend) the same, made there."""
        idx = idx.copy()
        bonus = np.zeros((*idx.shape, self.spec.n_agents), np.float32)
        for r, (m, b) in enumerate(zip(self.members, bonuses)):
            if b is not None:
                bonus[r] = b
            if not live[r]:
                idx[r] = self.frozen_draws(m)
        if self.replay.backend == "torch":
            return self.device_update_arrays(idx, bonus, live)
        cols = self.columns(self.replay.gather(idx), bonus, live)
        return [np.ascontiguousarray(c) for c in cols]

    def device_update_arrays(
        self, idx: np.ndarray, bonus: np.ndarray, live: list[bool]
    ) -> list[torch.Tensor]:
        """`update_arrays` with the replay on its device: the rows and the bonuses priced
        on the host go there in one copy (`send`), then one gather per field, the stored
        bonuses and the sum are made there: the values the host's way gives."""
        idx_t, bonus_t = send([idx, bonus], self.replay.device)
        cols = self.columns(self.replay.gather_on_device(idx_t), bonus_t, live)
        return [c.contiguous() for c in cols]

    def columns(self, g: dict[str, Any], bonus: Any, live: list[bool]) -> list[Any]:
        """The update's five columns from one gather `g` (numpy on the host, torch on a
        device: the same indexing and sum on either): a live run priced at collection
        takes its stored bonuses in place of `bonus`, rew gains the bonus per agent, and
        one shared minibatch loses its minibatch axis."""
        for r, m in enumerate(self.members):
            if live[r] and m.collection:
                bonus[r] = g["bonus"][r]
        cols = [g["obs"], g["act"], g["rew"][..., None] + bonus, g["next_obs"], g["done"]]
        if bonus.shape[1] == 1:  # one shared minibatch: no minibatch axis
            return [c[:, 0] for c in cols]
        return cols

    def frozen_draws(self, m: Member) -> np.ndarray:
        """A stopped run's fixed rows (`fixed_draws`), drawn once."""
        if m.frozen_draws is None:
            k = self.minibatches_per_update
            m.frozen_draws = fixed_draws(m.buffer, self.cfg.batch_size, k)
        return m.frozen_draws

    def cut_due(self) -> bool:
        """`cut_every_s` since the last cut (0: every point), and CUT_SPACING times the
        least of the recent cuts' seconds, up to CUT_MAX_WAIT_S. Which points cut changes
        no row: a resume from any of them is exact."""
        waited = time.monotonic() - self.last_cut
        if self.cut_every_s <= 0:
            return True
        recent = [spent for _, spent, *_ in self.cut_log[-CUT_SPACING_OVER:]]
        spacing = min(CUT_SPACING * min(recent), CUT_MAX_WAIT_S) if recent else 0.0
        return waited >= max(self.cut_every_s, spacing)

    def timing_snapshot(self, episode: int) -> dict[str, float]:
        """`timing` at this point, beside the loop's wall time and the process's CPU
        seconds and page faults so far (what bench_fig8.py takes differences of)."""
        use = resource.getrusage(resource.RUSAGE_SELF)
        return {
            "episode": episode,
            "wall": time.perf_counter() - self.start,
            **self.timing,
            "user_s": use.ru_utime,
            "sys_s": use.ru_stime,
            "minor_faults": use.ru_minflt,
        }

    def write_timing(self, folder: Path) -> None:
        """The snapshots as one JSON file per group in `folder`, named by its first run."""
        folder.mkdir(parents=True, exist_ok=True)
        first = self.members[0].out
        name = first.name if first is not None else f"pid{os.getpid()}"
        data = {
            "runs": [m.out.name if m.out else None for m in self.members],
            "torch_threads": torch.get_num_threads(),
            "blas": [(i["internal_api"], i["num_threads"]) for i in threadpool_info()],
            "points": self.timing_log,
        }
        (folder / f"timing-{name}.json").write_text(json.dumps(data) + "\n")

    def start_files(self) -> None:
        """Each run's provenance entry for this start (a resume adds its own: it may run
        elsewhere), its config.json, and its metrics files with the rows kept so far."""
        stats = self.learner.stats()
        for m in self.members:
            if m.out is None:
                continue
            m.out.mkdir(parents=True, exist_ok=True)
            start = provenance.entry(m.cfg.precision, stats, "trainer" if self.own else "group")
            if not self.own:
                start["group"] = {"runs": self.runs}
            if self.command is not None:  # one restart of a campaign, however many groups
                start["command"] = self.command
            if self.resumed:  # where the run went on from: a campaign's restarts, on its page
                start["resumed_at"] = self.first_episode - 1
                provenance.append(m.out / provenance.FILE, start)
            else:
                provenance.write(m.out / provenance.FILE, [start])
            # (whole or not at all: a resume refuses a config.json that does not read)
            write_config_json(m.out / "config.json", m.cfg.model_dump(mode="json"))
            m.writer = MetricsWriter(m.out, run_fields(m.cfg), rows=m.rows)

    def episode(self) -> None:
        c0, members, timing = self.cfg, self.members, self.timing
        clock = time.perf_counter
        for _ in range(c0.episode_len):
            t0 = clock()
            tr = self.collector.step(self.learner.act)
            if (why := nonfinite(tr, self.names)) is not None:
                raise WorldError(f"{why} in episode {members[0].env_steps // c0.episode_len + 1}")
            t1 = clock()
            timing["act_env"] += t1 - t0
            for r, m in enumerate(members):
                if m.stopped is not None:
                    continue  # (stopped by its rule: its world steps unread)
                m.collect(
                    tr.obs[r],
                    tr.act[r],
                    float(tr.rew[r]),
                    tr.next_obs[r],
                    float(tr.done[r]),
                    int(tr.collisions[r]),
                )
            self.replay.flush()  # (a device's replay: the step's rows in one copy)
            t2 = clock()
            timing["store_count"] += t2 - t1
            if max(m.env_steps for m in members) > c0.learning_starts:
                k = self.minibatches_per_update
                # (a run its early_stop rule ended: a fixed minibatch, nothing drawn or priced)
                live = [m.stopped is None for m in members]
                rngs = [m.sample_rng if on else None for m, on in zip(members, live)]
                idx = self.replay.draw(c0.batch_size, k, rngs)
                t3 = clock()
                bonuses = [
                    m.price(idx[r]) if on else None for r, (m, on) in enumerate(zip(members, live))
                ]
                t4 = clock()
                arrays = self.update_arrays(idx, bonuses, live)
                t5 = clock()
                self.learner.update(*arrays)
                timing["sample"] += (t3 - t2) + (t5 - t4)
                timing["price"] += t4 - t3
                timing["update"] += clock() - t5

    def point(self, episode: int) -> list[dict | None]:
        """Each run's row at this point (None for a run stopped by its rule)."""
        t0 = time.perf_counter()
        results = evaluate_group(
            self.learner.act, self.eval_venv, self.runs, self.cfg.eval_episodes
        )
        spent = time.perf_counter() - t0
        self.timing["eval"] += spent
        rows: list[dict | None] = []
        for m, ev in zip(self.members, results):
            if m.stopped is not None:
                rows.append(None)
                continue
            m.eval_s += spent
            wall = m.wall_before + time.perf_counter() - self.start
            row = metric_row(episode, ev, m, self.learner.updates, wall)
            m.rows.append(row)
            m.shift_warned = _say_if_constant_shift(m.rows, m.shift_warned, m.explorer.counting)
            rows.append(row)
        return rows

    # ------------------------------------------------------------------ cuts
    def cut(self, episode: int) -> None:
        """Each run's cut, in one run's format (its replay rows appended first): a run
        of a group resumes alone, and a run alone in a group."""
        t0 = time.perf_counter()
        replay_bytes = file_bytes = 0
        for r, m in enumerate(self.members):
            assert m.cuts is not None
            replay_bytes += m.append_pending()
            m_eval = self.m_eval
            rng = {
                "collector": self.collector.state(r),
                "sampler": dict(m.sample_rng.bit_generator.state),
                "eval_envs": [self.eval_venv.rng_state(r * m_eval + j) for j in range(m_eval)],
            }
            wall = m.wall_before + time.perf_counter() - self.start
            path = write_cut(
                m.cuts,
                episode,
                config=m.cfg.model_dump(mode="json"),
                learner=self.learner.run_state_dict(r),
                counters=m.counters(wall),
                rng=rng,
                tables=m.explorer.tables,
                replay_rows=m.replay_rows,
                torch_rng=torch.get_rng_state(),
            )
            file_bytes += path.stat().st_size
        self.last_cut = time.monotonic()
        spent = time.perf_counter() - t0
        self.cut_log.append((episode, spent, replay_bytes, file_bytes))
        self.timing["cut"] += spent
        log.debug("cut at episode %d in %.3f s", episode, spent)

    def restore(self) -> None:
        """Continue every run from its cut at the newest episode all runs have a cut of;
        the rows after it are dropped."""
        cuts = []
        for m in self.members:
            assert m.out is not None and m.cuts is not None
            config = m.cfg.model_dump(mode="json")
            check_resumable(m.out, config)
            cuts.append(latest_cut(m.cuts, config))
        episode = min(c.episode for c in cuts)
        for i, (m, c) in enumerate(zip(self.members, cuts)):
            if c.episode != episode:  # a group stopped while writing its runs' cuts
                assert m.cuts is not None
                path = m.cuts / f"cut-{episode:09d}.pt"
                if not path.exists():
                    raise CutError(f"{m.cuts}: no cut at episode {episode}, where the others are")
                cuts[i] = read_cut(path, m.cfg.model_dump(mode="json"))
        try:
            self.learner.load_run_state_dicts([c.state["learner"] for c in cuts])
        except (ValueError, KeyError, RuntimeError) as err:
            raise CutError(f"{cuts[0].path}: learner state does not fit: {err}") from None
        rngs = [c.state["rng"] for c in cuts]
        self.collector.load_state([rng["collector"] for rng in rngs])
        for r, (m, cut, rng) in enumerate(zip(self.members, cuts, rngs)):
            st = cut.state
            load_tables(m.explorer.tables, st["tables"], cut.path)
            m.refill(int(st["replay_rows"]), cut.path)
            m.sample_rng.bit_generator.state = rng["sampler"]
            for j, state in enumerate(rng["eval_envs"]):
                self.eval_venv.set_rng_state(r * self.m_eval + j, state)
            m.load_counters(st["counters"], cut.path)
            if m.cfg.early_stop is not None and m.rows:  # what the rows decided, again
                m.best = max(float(row["success_rate"]) for row in m.rows)
                if m.rows[-1].get("stop_reason"):  # (its checkpoint.pt written as it stopped)
                    m.stopped = (int(m.rows[-1]["episode"]), str(m.rows[-1]["stop_reason"]))
        torch.set_rng_state(cuts[0].state["torch_rng"])
        self.resumed = True
        self.first_episode = episode + 1
        log.info(
            "resuming %s from episode %d: %d transitions, %d updates",
            ", ".join(str(m.out) for m in self.members),
            episode,
            self.members[0].env_steps,
            self.learner.updates,
        )


def write_config_json(path: Path, config: dict) -> None:
    """The run's config.json, replaced whole (`atomic_write`)."""
    body = (json.dumps(config, indent=2) + "\n").encode()
    atomic_write(path, lambda f: f.write(body))


def check_resumable(out: Path, config: dict) -> None:
    """Refused before anything is loaded (the resume appends to the folder): a folder of
    another config, or a provenance file that does not read."""
    if why := folder_config_difference(out, config):
        raise CutError(f"{out}: holds a run of another config ({why})")
    try:
        provenance.read(out / provenance.FILE)
    except provenance.ProvenanceError as err:
        raise CutError(str(err)) from None


def _read_rows(path: Path, n: int, where: Path) -> list[dict]:
    """The first n metric rows written (a run killed after its last cut wrote more); a
    line among them that is not a row (two writers at once) is refused, naming it."""
    try:
        lines = path.read_text().splitlines()
    except OSError as err:
        raise CutError(f"{where}: cannot read the run's {path.name}: {err}") from None
    if len(lines) < n:
        raise CutError(f"{where}: needs {n} metric rows, {path} holds {len(lines)}")
    rows = []
    for i, line in enumerate(lines[:n], 1):
        try:
            rows.append(json.loads(line))
        except ValueError as err:
            raise CutError(f"{path}, line {i}: not a metric row ({err})") from None
    return rows
