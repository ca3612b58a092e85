"""The learner service: replay, updates at the thesis's replay ratio, weights, checkpoints.

A batch joins the replay buffer once the counter has acknowledged it (so every sampled
transition has been counted, n >= 1) and only once (`shared.protocol.ReceiveCursor`).
Exactly one update per ingested transition beyond `learning_starts`; actors get a
window of credits that closes while the learner is behind, so they wait rather than
let the ratio drift.

Bonuses are priced at sample time, one query per tick: a tick samples the minibatches
of all the updates it will do (up to UPDATES_PER_TICK, never past an episode boundary)
and asks the counter for their rows at once. Inbound messages are handled only
between ticks, so these are the minibatches per-update sampling would draw. One round
trip per tick instead of per update (docs/performance.md, "Learner service").

Weights go out at every episode boundary (once its updates are done), marked
`eval_point` every `eval_every` episodes. While the evaluator evaluates weights this
learner sent (`EvaluationsInFlight`), updates are marked contended so the thread tuner
can pick what is fastest beside it.
"""

from __future__ import annotations

import collections
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from services.common import ServiceBase
from shared import bus as keys
from shared.config import TrainConfig
from shared.exploration import BonusDiagnostics
from shared.factories import build_learner, minibatches_per_update
from shared.learners import Learner
from shared.networks import weights_as_arrays
from shared.protocol import AckTracker, ReceiveCursor
from shared.replay import ReplayBuffer, update_arrays
from shared.rollout import derive_seed
from shared.tasks import TaskSpec, task_spec_for
from shared.wire import WireError, check_dims, decode, encode

WINDOW_EPISODES = 2  # credits per actor, in episodes
MAX_BACKLOG_EPISODES = 2  # updates owed (per actor) before the window closes
UPDATES_PER_TICK = 20  # bound on work between inbox checks; one bonus query each
CHECKPOINT_EVERY_S = 60.0
# Phases of the learner's wall time that stats() reports per update; the bonus wait is
# BonusClient.wait_s, and what none of them covers (waiting for messages, acks, stats,
# and the wait for the first `learning_starts` transitions) is reported as "other".
TIME_PHASES = ("sample", "update", "publish", "inbound")


class BonusClient:
    """Bonus queries to the counter for sampled batches (local for none/constant)."""

    def __init__(self, svc: LearnerService, run: str, mode: str, beta: float, n: int) -> None:
        self.svc, self.run, self.mode, self.beta, self.n = svc, run, mode, beta, n
        self.latencies: collections.deque[float] = collections.deque(maxlen=1000)
        self.wait_s = 0.0  # all time spent in queries (the learner waits for each)
        self.failures = 0
        self.queries = 0
        self.rows = 0
        # The counter's table stats as of the last answered query (its reply carries
        # them): what an evaluation point reports, without a query of its own.
        self.tables: dict[str, float] | None = None
        self.fresh = False  # tables came with this tick's query
        # Each batch's (tables, B) counts from the last answered query, for diagnostics.
        self.counts: list[np.ndarray] = []

    def bonus_for(self, batches: list) -> list[np.ndarray] | None:
        """The (B, N) bonus of each sampled batch, priced in one query; None if the
        counter did not answer."""
        sizes = [len(b.rew) for b in batches]
        self.counts = [np.zeros((0, B), np.int64) for B in sizes]  # no tables to count
        if self.mode == "none":
            return [np.zeros((B, self.n), np.float32) for B in sizes]
        if self.mode == "constant":
            return [np.full((B, self.n), self.beta, np.float32) for B in sizes]
        rows = sum(sizes)
        t0 = time.perf_counter()
        obs = np.concatenate([b.obs for b in batches])
        act = np.concatenate([b.act for b in batches])
        payload = encode("bonus_query", self.run, obs=obs, act=act)
        try:
            replies = self.svc.bus.get(keys.k_bonus(self.run), payload, timeout=2.0)
        finally:
            self.wait_s += time.perf_counter() - t0
        for raw in replies:
            try:
                msg = decode(raw, "bonus_reply")
            except WireError as err:
                self.svc.reject(keys.k_bonus(self.run), str(err))
                continue
            if msg["bonus"].shape == (rows, self.n):
                self.latencies.append(time.perf_counter() - t0)
                self.queries += 1
                self.rows += rows
                self.tables = _table_stats(msg.get("tables"))
                self.fresh = True
                bonus = msg["bonus"].astype(np.float32)
                cuts = np.cumsum(sizes)[:-1]
                if msg["counts"].ndim == 2 and msg["counts"].shape[1] == rows:
                    self.counts = np.split(msg["counts"], cuts, axis=1)
                return np.split(bonus, cuts)
        self.failures += 1
        return None


class EvaluationsInFlight:
    """Evaluation points sent to the evaluator that it has not reported yet.

    `sent` is called on the learner's thread, `reported` on Zenoh's (from the
    evaluator's metric rows); each writes its own fields. A point unreported after
    `max_s` no longer counts (a slow or absent evaluator must not mark every update)."""

    def __init__(self, max_s: float = 1.0) -> None:
        self.max_s = max_s
        self.last_sent = -1
        self.sent_at = 0.0
        self.last_reported = -1
        self.reported_rows = 0

    def sent(self, point: int) -> None:
        self.last_sent, self.sent_at = point, time.monotonic()

    def reported(self, point: int) -> None:
        self.last_reported = max(self.last_reported, point)
        self.reported_rows += 1

    def busy(self) -> bool:
        """The evaluator is (most likely) evaluating a point we sent."""
        return self.last_reported < self.last_sent and time.monotonic() - self.sent_at < self.max_s


def _table_stats(raw: Any) -> dict[str, float] | None:
    """The reply's optional `tables` map, if well formed (numbers under known names)."""
    names = ("table_size", "count1_pct", "counted_transitions")
    if not isinstance(raw, dict) or not all(
        isinstance(raw.get(k), int | float) and not isinstance(raw.get(k), bool) for k in names
    ):
        return None
    return {k: raw[k] for k in names}


class Boundary(NamedTuple):
    """An ingested episode's end: weights go out once `updates` updates are done."""

    episode: int
    updates: int
    env_steps: int
    collisions_cum: int


@dataclass
class LearnerRun:
    """Everything the learner holds for the run it serves."""

    config: TrainConfig
    spec: TaskSpec
    learner: Learner
    buffer: ReplayBuffer
    rng: np.random.Generator
    actors: list[str]
    counter: str | None
    bonus: BonusClient
    evaluations: EvaluationsInFlight
    weights_pub: Callable[[bytes], None]
    eval_pub: Callable[[bytes], None]
    ack_pub: Callable[[bytes], None]
    received: ReceiveCursor  # what has been taken from each actor (whole episodes only)
    counted: AckTracker  # how far the counter has acknowledged each actor
    held: dict[str, collections.deque[dict[str, Any]]]  # received, not yet counted
    final: dict[str, int] = field(default_factory=dict)  # actor -> transitions it published
    ingested: int = 0
    episodes: int = 0
    collisions_cum: int = 0
    boundaries: collections.deque[Boundary] = field(default_factory=collections.deque)
    version: int = 0
    lags: collections.deque[int] = field(default_factory=lambda: collections.deque(maxlen=200))
    window_open: bool = True
    last_ack: float = 0.0
    last_stats: float = 0.0
    last_ckpt: float = field(default_factory=time.monotonic)
    t0: float = field(default_factory=time.perf_counter)
    bonus_means: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100)
    )
    # Wall time by phase (s): where the learner's time per update goes.
    time: dict[str, float] = field(default_factory=lambda: dict.fromkeys(TIME_PHASES, 0.0))
    contended_updates: int = 0
    diagnostics: BonusDiagnostics = field(default_factory=BonusDiagnostics)
    draws: int = 1  # minibatches per update (`minibatch: per-agent`: one per agent)

    @property
    def counting(self) -> bool:
        return self.config.explore in ("dis-macb", "cen-macb")

    @property
    def owed_total(self) -> int:
        """Updates the replay ratio asks for so far: one per transition after the warm-up."""
        return max(0, self.ingested - self.config.learning_starts)


class LearnerService(ServiceBase):
    role = "learner"

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        self.st: LearnerRun | None = None

    # ------------------------------------------------------------ run lifecycle
    def on_start(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        torch.set_num_threads(config.threads)
        self.listen(keys.k_transitions(run, "*"), "transitions", run)
        self.listen(keys.k_ack(run, "*"), "ack", run)
        self.listen(keys.k_status(run, "*"), "status", run)
        evaluations = EvaluationsInFlight()
        self.subscribe(
            keys.k_metrics(run, "eval"),
            lambda key, payload: self.on_eval_row(evaluations, key, payload),
            run,
        )
        spec = task_spec_for(config)
        actors = list(assign["actors"])
        self.st = LearnerRun(
            config=config,
            spec=spec,
            learner=build_learner(config, spec, contended=evaluations.busy),
            buffer=ReplayBuffer(
                min(config.buffer_size, config.episodes * config.episode_len),
                spec.joint_obs_dim,
                spec.joint_act_dim,
            ),
            rng=np.random.default_rng(derive_seed(config.seed, "sampler")),
            actors=actors,
            counter=assign.get("counter"),
            bonus=BonusClient(self, run, config.explore, config.beta, spec.n_agents),
            evaluations=evaluations,
            weights_pub=self.bus.publisher(keys.k_weights(run, "latest")),
            eval_pub=self.bus.publisher(keys.k_weights(run, "eval")),
            ack_pub=self.bus.publisher(keys.k_ack(run, self.id)),
            received=ReceiveCursor(actors=actors, partial=False),
            counted=AckTracker(actors),
            held={a: collections.deque() for a in actors},
            draws=minibatches_per_update(config),
        )
        self.publish_weights(eval_point=-1)  # version 0: every actor starts from these
        self.publish_status(run, "running", actors=actors)

    def on_stop(self, run: str, reason: str) -> None:
        self.checkpoint()
        self.st = None

    def on_shutdown(self) -> None:
        if self.st is not None:
            self.checkpoint()

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        t0 = time.perf_counter()
        try:
            self._handle(tag, key, payload)
        finally:
            if self.st is not None:
                self.st.time["inbound"] += time.perf_counter() - t0

    def _handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "reject":  # found malformed on another thread (on_eval_row)
            self.reject(key, payload.decode(errors="replace"))
        elif tag == "transitions":
            msg = self.decode_for_run(key, payload, "transitions")
            if msg is not None:
                self.on_transitions(key, msg)
        elif tag == "ack":
            msg = self.decode_for_run(key, payload, "ack")
            if msg is not None and self.st is not None and msg["service"] == self.st.counter:
                for actor, seq in msg["acked"].items():
                    self.st.counted.ack(actor, seq)
                self.release_counted()
        elif tag == "status":
            msg = self.decode_for_run(key, payload, "status")
            st = self.st
            if msg is not None and st is not None and msg["service"] in st.actors:
                if msg["state"] == "completed":
                    st.final[msg["service"]] = int(msg["detail"].get("final_seq", 0))
                elif msg["state"] == "failed":
                    self.fail(f"actor {msg['service']} failed: {msg['detail']}")

    def on_eval_row(self, evaluations: EvaluationsInFlight, key: str, payload: bytes) -> None:
        """The evaluator's metric row for a point (on Zenoh's thread): that evaluation
        is over. Only the point is read; the API is the rows' consumer of record. A
        malformed row is counted and logged on the service's thread (via the inbox),
        which owns the reject counts that stats() reads."""
        try:
            msg = decode(payload, "metrics")
            point = msg["data"]["episode"]
            if not isinstance(point, int) or isinstance(point, bool):
                raise WireError(f"metrics: eval row episode is not an int: {point!r}")
        except (WireError, KeyError) as err:
            self.inbox.put(("reject", key, str(err).encode()))
            return
        evaluations.reported(point)

    def on_transitions(self, key: str, msg: dict[str, Any]) -> None:
        st = self.st
        assert st is not None
        actor = msg["actor"]
        if not st.received.knows(actor):
            self.reject(key, f"unknown actor: {actor}")
            return
        check_dims(msg, st.spec.joint_obs_dim, st.spec.joint_act_dim)
        n = len(msg["rew"])
        if n != st.config.episode_len:
            raise WireError(
                f"transitions: a batch is one episode ({st.config.episode_len}), got {n}"
            )
        # A duplicate (a resend) or a gap is not taken; either way the ack tells the
        # actor again where we are, and it resends from there.
        if st.received.take(actor, msg["seq"], n).took:
            st.held[actor].append(msg)
            self.release_counted()
        self.send_ack()

    def release_counted(self) -> None:
        """Move batches the counter has counted (or all, with no counting) into replay."""
        st = self.st
        assert st is not None
        for actor, held in st.held.items():
            while held and (
                not st.counting or st.counted.covers(actor, held[0]["seq"], len(held[0]["rew"]))
            ):
                self.ingest(held.popleft())

    def ingest(self, msg: dict[str, Any]) -> None:
        st = self.st
        assert st is not None
        st.buffer.add(msg["obs"], msg["act"], msg["rew"], msg["next_obs"], msg["done"])
        st.ingested += len(msg["rew"])
        st.episodes += 1
        st.collisions_cum += int(msg["collisions"].sum())
        st.lags.append(st.version - msg["policy_version"])
        st.boundaries.append(Boundary(st.episodes, st.owed_total, st.ingested, st.collisions_cum))

    # ------------------------------------------------------------ work
    def tick(self) -> bool:
        st = self.st
        if st is None:
            return False
        cfg, learner = st.config, st.learner
        owed = st.owed_total - learner.updates
        todo = min(owed, UPDATES_PER_TICK)
        if st.boundaries:
            todo = min(todo, max(0, st.boundaries[0].updates - learner.updates))
        spent = st.time
        t0 = time.perf_counter()
        draws = st.draws  # minibatches per update: 1, or one per agent
        batches = [st.buffer.sample(cfg.batch_size, st.rng) for _ in range(todo * draws)]
        spent["sample"] += time.perf_counter() - t0
        st.bonus.fresh = False
        bonuses = st.bonus.bonus_for(batches) if batches else []
        if bonuses is None:  # counter silent (restarting?): draw again on the next tick
            batches, bonuses = [], []
        t0 = time.perf_counter()
        evaluating = st.evaluations.busy
        counts = st.bonus.counts if len(st.bonus.counts) == len(bonuses) else None
        for u in range(len(batches) // draws):
            mine = slice(u * draws, (u + 1) * draws)
            # Counted here for every kind of learner; a tuned one polls the same signal
            # for its tuners and its own count (in its stats(), which take precedence).
            contended = evaluating()
            st.contended_updates += contended
            learner.update(*update_arrays(batches[mine], bonuses[mine]))
            for j in range(mine.start, mine.stop):
                st.bonus_means.append(float(bonuses[j].mean()))
                st.diagnostics.record(bonuses[j], counts[j] if counts is not None else [])
            owed -= 1
        t1 = time.perf_counter()
        spent["update"] += t1 - t0
        self.pass_boundaries()
        spent["publish"] += time.perf_counter() - t1
        now = time.monotonic()
        window_open = owed < MAX_BACKLOG_EPISODES * cfg.episode_len * len(st.actors)
        if window_open != st.window_open or now - st.last_ack > 0.5:
            st.window_open = window_open
            self.send_ack()
        if now - st.last_stats > 1.0:
            st.last_stats = now
            self.publish_metrics(self.run_id, self.stats(), source="learner")
        if now - st.last_ckpt > CHECKPOINT_EVERY_S:
            self.checkpoint()
        self.maybe_finish()
        return owed > 0 and self.st is not None

    def pass_boundaries(self) -> None:
        """Publish weights at each episode boundary whose updates are done."""
        st = self.st
        assert st is not None
        while st.boundaries and st.learner.updates >= st.boundaries[0].updates:
            b = st.boundaries.popleft()
            is_eval = b.episode % st.config.eval_every == 0 or b.episode == st.config.episodes
            self.publish_weights(
                eval_point=b.episode if is_eval else -1,
                episode=b.episode,
                env_steps=b.env_steps,
                collisions=b.collisions_cum,
            )

    def publish_weights(
        self, eval_point: int, episode: int = 0, env_steps: int = 0, collisions: int = 0
    ) -> None:
        st = self.st
        assert st is not None
        if episode:  # version 0 is the initial weights; each boundary makes a new one
            st.version += 1
        payload = encode(
            "weights",
            self.run_id,
            version=st.version,
            updates=st.learner.updates,
            env_steps=env_steps,
            episodes=episode,
            eval_point=eval_point,
            collisions_cum=collisions,
            actors=weights_as_arrays(st.learner.actor_weights()),
            info={
                **self.stats(),
                "counter": self.counter_stats() if eval_point >= 0 else {},
                # What the bonus did on the rows sampled since the last point.
                "bonus": st.diagnostics.take() if eval_point >= 0 else {},
            },
        )
        if eval_point >= 0:
            st.eval_pub(payload)
            st.evaluations.sent(eval_point)
        else:
            st.weights_pub(payload)

    def counter_stats(self) -> dict[str, Any]:
        """The counter's stats for this run now (table size, count-1 %, counted): from the
        reply to this tick's bonus query when there was one, else by asking the counter."""
        st = self.st
        assert st is not None
        if st.bonus.tables is not None and st.bonus.fresh:
            return dict(st.bonus.tables)
        if not st.counter:
            return {}
        for raw in self.bus.get(keys.k_info("counter", st.counter), timeout=1.0):
            try:
                return dict(json.loads(raw).get("runs", {}).get(self.run_id, {}))
            except (ValueError, AttributeError, TypeError):
                return {}
        return {}

    def send_ack(self) -> None:
        st = self.st
        assert st is not None
        st.last_ack = time.monotonic()
        window = WINDOW_EPISODES * st.config.episode_len if st.window_open else 0
        st.ack_pub(
            encode(
                "ack",
                self.run_id,
                service=self.id,
                acked=st.received.positions(),
                window=window,
            )
        )

    def stats(self) -> dict[str, Any]:
        st = self.st
        assert st is not None
        updates = st.learner.updates
        owed_total = st.owed_total
        wall = time.perf_counter() - st.t0
        lat = sorted(st.bonus.latencies)
        per_update = 1e3 / updates if updates else 0.0
        phases = {**st.time, "bonus_wait": st.bonus.wait_s}
        spent = {f"ms_per_update_{k}": v * per_update for k, v in phases.items()}
        spent["ms_per_update_other"] = (wall - sum(phases.values())) * per_update
        return {
            "updates": updates,
            "ingested": st.ingested,
            "episodes_ingested": st.episodes,
            "replay_ratio": updates / owed_total if owed_total else 0.0,
            "policy_lag": float(np.mean(st.lags)) if st.lags else 0.0,
            "policy_version": st.version,
            "wall_s": wall,
            "steps_per_sec": st.ingested / wall if wall > 0 else 0.0,
            "updates_per_sec": updates / wall if wall > 0 else 0.0,
            "backlog": owed_total - updates,
            "window_open": st.window_open,
            "bonus_p50_ms": 1e3 * lat[len(lat) // 2] if lat else 0.0,
            "bonus_p99_ms": 1e3 * lat[int(len(lat) * 0.99)] if lat else 0.0,
            "bonus_wait_ms_per_update": spent["ms_per_update_bonus_wait"],
            "bonus_queries": st.bonus.queries,
            "bonus_rows_per_query": st.bonus.rows / max(1, st.bonus.queries),
            "bonus_failures": st.bonus.failures,
            "bonus_mean": float(np.mean(st.bonus_means)) if st.bonus_means else 0.0,
            "rejects_total": sum(self.rejects.values()),
            "contended_updates": st.contended_updates,
            "eval_rows_seen": st.evaluations.reported_rows,
            **spent,
            **st.learner.stats(),
        }

    def maybe_finish(self) -> None:
        st = self.st
        assert st is not None
        if set(st.final) != set(st.actors):
            return
        if any(st.received.expected(a) < st.final[a] for a in st.actors):
            return
        if any(st.held[a] for a in st.actors) or st.boundaries:
            return
        if st.learner.updates < st.owed_total:
            return
        run = self.run_id
        self.checkpoint()
        stats = self.stats()
        self.publish_metrics(run, stats, source="learner")
        self.publish_status(run, "completed", **stats)
        self.log.info("run %s completed: %s", run, json.dumps(stats))
        self.st = None
        self.free(run)

    def on_peer_lost(self, role: str, peer: str) -> None:
        """An actor that dies mid-run fails the run: its transitions cannot come."""
        st = self.st
        if role == "actor" and st is not None and peer in st.actors and peer not in st.final:
            self.fail(f"actor {peer} died before it finished its episodes")

    def fail(self, reason: str) -> None:
        run = self.run_id
        self.log.error("run %s failed: %s", run, reason)
        self.publish_status(run, "failed", reason=reason)
        self.st = None
        self.free(run)

    def checkpoint(self) -> None:
        """Networks, optimizers and step counters, loadable with weights_only=True."""
        st = self.st
        if st is None:
            return
        st.last_ckpt = time.monotonic()
        out = self.data_dir / "learner" / self.run_id
        out.mkdir(parents=True, exist_ok=True)
        state = {
            "config": json.dumps(st.config.model_dump(mode="json")),
            "learner": st.learner.state_dict(),
            "counters": {
                "ingested": st.ingested,
                "episodes": st.episodes,
                "updates": st.learner.updates,
                "expected": st.received.positions(),
                "version": st.version,
            },
        }
        tmp = out / "checkpoint.tmp"
        torch.save(state, tmp)
        tmp.replace(out / "checkpoint.pt")


def make_service(service_id: str, connect: list[str], data_dir: Path) -> LearnerService:
    return LearnerService(service_id, connect, data_dir)
