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
from shared.core.exploration import BonusDiagnostics, CountExploration, constant_shift
from shared.core.learners import Learner
from shared.core.replay import ReplayBuffer, update_arrays
from shared.envs.tasks import make_task_for
from shared.metrics import TRAIN_FIELDS
from shared.persist import checkpoint, provenance
from shared.persist.checkpoint import CutError, config_difference, load_tables
from shared.persist.cuts import ReplayLog, latest_cut, write_cut
from shared.persist.cuts import clear as clear_cuts
from shared.persist.files import read_json
from shared.run.factories import build_exploration, build_learner, minibatches_per_update
from shared.run.rollout import derive_seed, evaluate, make_collector

log = logging.getLogger("macb.trainer")

# A cut at the first evaluation point after this many seconds since the last one (and at
# the end): at ~150 env steps/s that is every ~9,000 transitions, whose replay rows and
# the learner's state are what a cut writes (docs/reliability.md).
DEFAULT_CUT_EVERY_S = 60.0

METRIC_FIELDS = TRAIN_FIELDS


class MetricsWriter:
    """Appends rows to metrics.csv and metrics.jsonl as they are produced; `rows` (a
    resumed run's rows up to its cut) are written first, replacing what was there."""

    def __init__(
        self, out: Path, fields: tuple[str, ...] = METRIC_FIELDS, rows: list[dict] = ()
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


def metric_row(episode: int, ev, run, updates: int, wall: float) -> dict:
    """One evaluation point's row: `run` has the run's counters (`env_steps`,
    `collisions_cum`, `eval_s`), `explorer` and `diagnostics` (a `Run` or a group's
    `Member`)."""
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
    }


def price_at_collection(
    explorer: CountExploration,
    obs: np.ndarray,
    act: np.ndarray,
    diagnostics: BonusDiagnostics,
    on: bool,
) -> np.ndarray | None:
    """`bonus_at: collection`: the just-counted transition's per-agent bonus (N,), from
    its count including itself, to store with it (the diagnostics then describe the
    collected transitions); None when bonuses are priced at sample time."""
    if not on:
        return None
    counts = explorer.counts(obs[None], act[None])
    bonus = explorer.bonus_from_counts(counts, 1)
    diagnostics.record(bonus, counts)
    return bonus[0]


def price_batches(
    explorer: CountExploration, batches: list, diagnostics: BonusDiagnostics
) -> list[np.ndarray]:
    """Each sampled minibatch's per-agent bonus: the stored one (`bonus_at: collection`),
    or priced now from the current counts (recorded in the diagnostics)."""
    bonuses = []
    for b in batches:
        if b.bonus is not None:
            bonuses.append(b.bonus)
            continue
        counts = explorer.counts(b.obs, b.act)
        bonuses.append(explorer.bonus_from_counts(counts, len(b.rew)))
        diagnostics.record(bonuses[-1], counts)
    return bonuses


def train(
    cfg: TrainConfig,
    out: Path | None,
    progress: bool = True,
    on_metrics: Callable[[dict], None] | None = None,
    stop_when: Callable[[dict], bool] | None = None,
    resume: bool = False,
    cut_every_s: float = DEFAULT_CUT_EVERY_S,
) -> list[dict]:
    """Run one experiment; returns the metric rows (also written under `out`).

    `stop_when(row)` returning True ends the run early after that evaluation. With
    `out`, a cut (shared/persist/cuts.py) is written at an evaluation point whenever
    `cut_every_s` seconds have passed since the last one, and at the end; `resume`
    continues from the newest usable cut in `out` (its config.json must equal `cfg`),
    keeping the rows written up to it, so the rows come out as without the stop.

    numpy's BLAS (the SimHash projections) runs on one thread while it trains, as in
    `macb train` and the services, which set it before numpy loads: from Python, numpy
    is usually loaded already with a thread per core, and the k=512 projections of a
    100-row batch then kept a second core busy (1.03 cores for counting against 0.04,
    bench_scaling) beside torch's own threads. The caller's setting is restored after.
    """
    if resume and out is None:
        raise ValueError("resume needs the run's output folder")
    with threadpool_limits(limits=1, user_api="blas"):
        run = Run(cfg, out, cut_every_s)
        if resume:
            run.restore()
        elif run.cuts is not None and run.cuts.exists():
            clear_cuts(run.cuts)  # a fresh run: an earlier run's cuts are not its own
        return run.go(progress, on_metrics, stop_when)


class Run:
    """One run's parts and counters: the loop, its cuts and their restore."""

    def __init__(self, cfg: TrainConfig, out: Path | None, cut_every_s: float) -> None:
        torch.set_num_threads(cfg.threads)
        self.cfg, self.out, self.cut_every_s = cfg, out, cut_every_s
        self.env = make_task_for(cfg)
        spec = self.spec = self.env.spec
        self.eval_envs = [make_task_for(cfg) for _ in range(min(cfg.eval_episodes, 10))]
        for j, e in enumerate(self.eval_envs):
            e.reset(seed=derive_seed(cfg.seed, "eval", j))
        self.learner = build_learner(cfg, spec)
        self.explorer = build_exploration(cfg, spec)
        capacity = min(cfg.buffer_size, cfg.episodes * cfg.episode_len)
        # bonus_at collection: priced once, when collected, and stored with the reward
        self.collection = cfg.bonus_at == "collection"
        stored = spec.n_agents if self.collection else 0
        self.buffer = ReplayBuffer(capacity, spec.joint_obs_dim, spec.joint_act_dim, stored)
        self.collector = make_collector(cfg, self.env)
        self.sample_rng = np.random.default_rng(derive_seed(cfg.seed, "sampler"))
        self.minibatches_per_update = minibatches_per_update(cfg)
        self.diagnostics = BonusDiagnostics()
        self.rows: list[dict] = []
        self.shift_warned = False
        self.first_episode = 1
        self.resumed = False
        self.env_steps = self.collisions_cum = 0
        self.eval_s = self.wall_before = 0.0  # time spent in earlier lives of the run
        self.width = {
            "obs": spec.joint_obs_dim,
            "act": spec.joint_act_dim,
            "rew": 1,
            "next_obs": spec.joint_obs_dim,
            "done": 1,
        }
        if self.collection:
            self.width["bonus"] = spec.n_agents
        self.cuts = self.replay = None
        self.replay_rows = 0  # rows of the replay log on disk, as of the last cut
        self.last_cut = time.monotonic()
        # (episode, seconds, replay bytes appended, cut file bytes) of each cut written.
        self.cut_log: list[tuple[int, float, int, int]] = []
        # Every transition collected, kept since the last cut for the replay log.
        self.pending: list[tuple[np.ndarray, ...]] = []
        if out is not None:
            self.cuts = out / "cuts"
            self.replay = ReplayLog(self.cuts)

    # ------------------------------------------------------------------ the loop
    def go(self, progress, on_metrics, stop_when) -> list[dict]:
        cfg, out = self.cfg, self.out
        writer = None
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            # What this start runs on (a resume adds its own entry: it may be elsewhere).
            start = provenance.entry(cfg.precision, self.learner.stats(), "trainer")
            if self.resumed:
                provenance.append(out / provenance.FILE, start)
            else:
                provenance.write(out / provenance.FILE, [start])
            config = json.dumps(cfg.model_dump(mode="json"), indent=2) + "\n"
            (out / "config.json").write_text(config)
            writer = MetricsWriter(out, rows=self.rows)
        bar = None
        if progress:
            from tqdm import tqdm

            desc = f"{cfg.task} {cfg.algo}+{cfg.explore}"
            bar = tqdm(total=cfg.episodes, initial=self.first_episode - 1, unit="ep", desc=desc)
        self.start = time.perf_counter()
        try:
            for episode in range(self.first_episode, cfg.episodes + 1):
                self.episode()
                if episode % cfg.eval_every == 0 or episode == cfg.episodes:
                    row = self.point(episode)
                    if writer:
                        writer.write(row)
                    if self.cuts is not None and (
                        len(self.rows) == 1  # a run killed in its first minute resumes too
                        or time.monotonic() - self.last_cut >= self.cut_every_s
                        or episode == cfg.episodes
                    ):
                        self.cut(episode)
                    if on_metrics:
                        on_metrics(row)
                    if bar:
                        bar.set_postfix(
                            success=f"{row['success_rate']:.2f}",
                            sps=f"{row['steps_per_sec']:.0f}",
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
            episodes = self.rows[-1]["episode"] if self.rows else 0
            counters = {
                "env_steps": self.env_steps,
                "episodes": episodes,
                "updates": self.learner.updates,
            }
            save_checkpoint(out / "checkpoint.pt", self.learner, self.explorer, counters, cfg)
            log.info("wrote %s", out)
        return self.rows

    def episode(self) -> None:
        cfg, explorer, buffer = self.cfg, self.explorer, self.buffer
        for _ in range(cfg.episode_len):
            tr = self.collector.step(self.learner.act)
            explorer.observe(tr.obs[None], tr.act[None])
            diag = self.diagnostics
            stored = price_at_collection(explorer, tr.obs, tr.act, diag, self.collection)
            buffer.add(tr.obs, tr.act, tr.rew, tr.next_obs, tr.done, stored)
            if self.replay is not None:
                row = (tr.obs, tr.act, tr.rew, tr.next_obs, tr.done)
                self.pending.append(row if stored is None else (*row, stored))
            self.env_steps += 1
            self.collisions_cum += tr.collisions
            if self.env_steps > cfg.learning_starts:
                batches = [
                    buffer.sample(cfg.batch_size, self.sample_rng)
                    for _ in range(self.minibatches_per_update)
                ]
                bonuses = price_batches(explorer, batches, self.diagnostics)
                self.learner.update(*update_arrays(batches, bonuses))

    def point(self, episode: int) -> dict:
        t0 = time.perf_counter()
        ev = evaluate(self.learner.act, self.eval_envs, self.cfg.eval_episodes)
        self.eval_s += time.perf_counter() - t0
        wall = self.wall_before + time.perf_counter() - self.start
        row = metric_row(episode, ev, self, self.learner.updates, wall)
        self.rows.append(row)
        self.shift_warned = _say_if_constant_shift(
            self.rows, self.shift_warned, self.explorer.counting
        )
        return row

    # ------------------------------------------------------------------ cuts
    def cut(self, episode: int) -> None:
        """Replay rows since the last cut appended, then the cut itself (atomic)."""
        assert self.cuts is not None and self.replay is not None
        t0 = time.perf_counter()
        replay_bytes = append_pending(self, self.width)
        rng = {
            "collector": self.collector.state(),
            "sampler": dict(self.sample_rng.bit_generator.state),
            "eval_envs": [e.rng_state() for e in self.eval_envs],
        }
        wall = self.wall_before + time.perf_counter() - self.start
        path = write_cut(
            self.cuts,
            episode,
            config=self.cfg.model_dump(mode="json"),
            learner=self.learner.state_dict(),
            counters=cut_counters(self, wall),
            rng=rng,
            tables=self.explorer.tables,
            replay_rows=self.replay_rows,
            torch_rng=torch.get_rng_state(),
        )
        self.last_cut = time.monotonic()
        spent = time.perf_counter() - t0
        self.cut_log.append((episode, spent, replay_bytes, path.stat().st_size))
        log.debug("cut at episode %d in %.3f s", episode, spent)

    def restore(self) -> None:
        """Continue from the newest usable cut in `out`; the rows after it are dropped."""
        assert self.out is not None and self.cuts is not None and self.replay is not None
        config = self.cfg.model_dump(mode="json")
        check_resumable(self.out, config)
        self.resumed = True
        cut = latest_cut(self.cuts, config)
        st = cut.state
        try:
            self.learner.load_state_dict(st["learner"])
        except (ValueError, KeyError, RuntimeError) as err:
            raise CutError(f"{cut.path}: learner state does not fit: {err}") from None
        load_tables(self.explorer.tables, st["tables"], cut.path)
        refill(self, int(st["replay_rows"]), self.width, cut.path)
        rng = st["rng"]
        self.collector.load_state(rng["collector"])
        self.sample_rng.bit_generator.state = rng["sampler"]
        for e, state in zip(self.eval_envs, rng["eval_envs"], strict=True):
            e.set_rng_state(state)
        torch.set_rng_state(st["torch_rng"])
        load_counters(self, st["counters"], self.out, cut.path)
        self.first_episode = cut.episode + 1
        log.info(
            "resuming %s from %s: episode %d, %d transitions, %d updates",
            self.out,
            cut.path.name,
            cut.episode,
            self.env_steps,
            self.learner.updates,
        )


# ------------------------------------------------------------------ one run's cut
# A `Run` and a group's `Member` keep the same per-run fields (replay, pending,
# replay_rows, collection, buffer, the counters); a group writes each run's cut in this
# same format, so a run of a group resumes alone with `macb train --resume`.


def append_pending(run, width: dict[str, int]) -> int:
    """The transitions collected since the last cut, onto the run's replay log; bytes."""
    if not run.pending:
        return 0
    cols = list(zip(*run.pending))
    arrays = {
        "obs": np.stack(cols[0]),
        "act": np.stack(cols[1]),
        "rew": np.asarray(cols[2], np.float32),
        "next_obs": np.stack(cols[3]),
        "done": np.asarray(cols[4], np.float32),
    }
    if run.collection:
        arrays["bonus"] = np.stack(cols[5])
    written = run.replay.append(arrays, run.replay_rows, width)
    run.replay_rows += len(run.pending)
    run.pending = []
    return written


def check_resumable(out: Path, config: dict) -> None:
    """Refused before anything is loaded (the resume appends to the folder): a folder of
    another config, or a provenance file that does not read."""
    written = read_json(out / "config.json")
    if written is not None and (diff := config_difference(written, config)):
        raise CutError(f"{out / 'config.json'}: another config ({diff})")
    try:
        provenance.read(out / provenance.FILE)
    except provenance.ProvenanceError as err:
        raise CutError(str(err)) from None


def refill(run, replay_rows: int, width: dict[str, int], where: Path) -> None:
    """The replay buffer as it was at the cut: the log's last `capacity` rows, each at
    the slot it had (row r at r % capacity), so sampling goes on as without the stop."""
    run.replay_rows = replay_rows
    data = run.replay.read(replay_rows, width, where)
    buffer = run.buffer
    first = replay_rows - min(replay_rows, buffer.capacity)
    buffer.added = first
    buffer.pos = first % buffer.capacity
    buffer.add(
        *(data[k][first:] for k in ("obs", "act", "rew", "next_obs", "done")),
        data["bonus"][first:] if run.collection else None,
    )


def cut_counters(run, wall: float) -> dict:
    return {
        "env_steps": run.env_steps,
        "collisions_cum": run.collisions_cum,
        "rows": len(run.rows),
        "shift_warned": run.shift_warned,
        "eval_s": run.eval_s,
        "wall_s": wall,
    }


def load_counters(run, c: dict, out: Path, where: Path) -> None:
    """`cut_counters` back, and the metric rows written up to the cut."""
    run.env_steps, run.collisions_cum = int(c["env_steps"]), int(c["collisions_cum"])
    run.shift_warned = bool(c["shift_warned"])
    run.eval_s, run.wall_before = float(c["eval_s"]), float(c["wall_s"])
    run.rows = _read_rows(out / "metrics.jsonl", int(c["rows"]), where)


def _read_rows(path: Path, n: int, where: Path) -> list[dict]:
    """The first n metric rows written (a run killed after its last cut wrote more)."""
    try:
        lines = path.read_text().splitlines()
    except OSError as err:
        raise CutError(f"{where}: cannot read the run's {path.name}: {err}") from None
    if len(lines) < n:
        raise CutError(f"{where}: needs {n} metric rows, {path} holds {len(lines)}")
    return [json.loads(line) for line in lines[:n]]
