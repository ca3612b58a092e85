"""The learner service: replay, updates at the thesis's replay ratio, weights, checkpoints.

Transitions arrive from actors, numbered per actor. A batch joins the replay
buffer once the counter has acknowledged it (so every sampled transition has been
counted, n >= 1) and only once (duplicates and gaps are handled by sequence
number). The learner does exactly one update per ingested transition beyond the
first `learning_starts`; it grants actors a window of credits that closes while it
is behind, so actors wait rather than let the ratio drift.

Bonuses are asked of the counter at sample time, answered before the updates run:
each tick samples the minibatches of all the updates it will do (up to
UPDATES_PER_TICK, never past an episode boundary) and prices their rows in one query.
The buffer cannot change within a tick (inbound messages are handled between ticks),
so these are the minibatches per-update sampling would draw from the same generator,
and the counts are those the counter holds when the tick starts: per-update queries
would see at most the batches the counter takes during the tick, a timing the
cluster never fixed anyway (the counter runs ahead of the learner's buffer by up to
a few episodes). One round trip per tick instead of per update: a 2,000-row query
took 8-13 ms p50 in bench_e2e's cluster (~1.9 ms of it the counter's work), i.e.
0.4-0.7 ms per update, where per-update queries cost 1.75-2 ms each (~18% of the
learner's time). (An overlapped variant, asking for batch k+1 while update k ran,
learned visibly worse on sparse `simple` in a small sample, 0 of 4 against 2 of 3
reaching 80% by episode 400, for reasons not understood; this one overlaps nothing.)

Tried and left out (docs/performance.md, section "Session 3"): splitting a tick's
query in three so the first update waits for 100 rows only (the wait is the round
trip, 8-13 ms whatever the size: no gain); asking for the next tick's minibatches a
tick ahead, which needs the inbox handled before each tick (the loop ticks after
every message, so each tick used to start with exactly one episode owed). That cut
the learner's wait from ~0.6 to ~0.2 ms per update but not its time, likely because
the actor's episodes then ran during the learner's two-thread updates instead of in
its waits.

Weights go out at every episode boundary of training (when the updates owed for
that episode are done), marked `eval_point` every `eval_every` episodes, which is
what the evaluator evaluates.

While the evaluator evaluates weights this learner sent (from the send until its
metric row for that point arrives: `EvaluationsInFlight`), updates are marked
contended: with `learner_lanes: auto` a tuner of their own picks their threads. On
a 2-core machine the evaluation (~20 ms of episodes) starts with every tick, and an
update on two OpenMP threads then waits for the thread the evaluator preempted: the
first update of a tick took 17-28 ms against 5-8 ms for the rest (per-update trace of
bench_e2e's cluster); on one thread it takes 11-14 ms. The cluster ran a median 5%
faster than without this in 10 alternated pairs (7% over 19 pairs, counting 9 of a
version that forced one thread instead of tuning; docs/performance.md, "Session 4").
"""

from __future__ import annotations

import collections
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.common import ServiceBase
from shared import bus as keys
from shared.config import TrainConfig
from shared.factories import build_learner
from shared.networks import weights_as_arrays
from shared.replay import ReplayBuffer
from shared.rollout import derive_seed
from shared.tasks import task_spec
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

    def bonus_for(self, batches: list) -> list[np.ndarray] | None:
        """The (B, N) bonus of each sampled batch, priced in one query; None if the
        counter did not answer."""
        sizes = [len(b.rew) for b in batches]
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
                return np.split(bonus, np.cumsum(sizes)[:-1])
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


class LearnerService(ServiceBase):
    role = "learner"

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        self.r: dict[str, Any] = {}

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
        spec = task_spec(config.task, config.agents, config.episode_len)
        actors = list(assign["actors"])
        learner = build_learner(config, spec, contended=evaluations.busy)
        self.r = {
            "spec": spec,
            "learner": learner,
            "buffer": ReplayBuffer(
                min(config.buffer_size, config.episodes * config.episode_len),
                spec.joint_obs_dim,
                spec.joint_act_dim,
            ),
            "rng": np.random.default_rng(derive_seed(config.seed, "sampler")),
            "actors": actors,
            "counter": assign.get("counter"),
            "expected": dict.fromkeys(actors, 0),  # next seq taken from each actor
            "counter_acked": dict.fromkeys(actors, 0),
            "held": {a: collections.deque() for a in actors},  # received, not yet counted
            "final": {},  # actor -> number of transitions it published in all
            "ingested": 0,
            "episodes": 0,
            "collisions_cum": 0,
            "boundaries": collections.deque(),  # (episode, updates target)
            "version": 0,
            "lags": collections.deque(maxlen=200),
            "window_open": True,
            "last_ack": 0.0,
            "last_stats": 0.0,
            "last_ckpt": time.monotonic(),
            "t0": time.perf_counter(),
            "bonus": BonusClient(self, run, config.explore, config.beta, spec.n_agents),
            "weights_pub": self.bus.publisher(keys.k_weights(run, "latest")),
            "eval_pub": self.bus.publisher(keys.k_weights(run, "eval")),
            "ack_pub": self.bus.publisher(keys.k_ack(run, self.id)),
            "bonus_means": collections.deque(maxlen=100),
            # Wall time by phase (s): where the learner's time per update goes.
            "time": dict.fromkeys(TIME_PHASES, 0.0),
            "evaluations": evaluations,
            "contended_updates": 0,
        }
        self.publish_weights(eval_point=-1)  # version 0: every actor starts from these
        self.publish_status(run, "running", actors=actors)

    def on_stop(self, run: str, reason: str) -> None:
        self.checkpoint()
        self.r = {}

    def on_shutdown(self) -> None:
        if self.r:
            self.checkpoint()

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        t0 = time.perf_counter()
        try:
            self._handle(tag, key, payload)
        finally:
            if self.r:
                self.r["time"]["inbound"] += time.perf_counter() - t0

    def _handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "reject":  # found malformed on another thread (on_eval_row)
            self.reject(key, payload.decode(errors="replace"))
        elif tag == "transitions":
            msg = self.decode_for_run(key, payload, "transitions")
            if msg is not None:
                self.on_transitions(key, msg)
        elif tag == "ack":
            msg = self.decode_for_run(key, payload, "ack")
            if msg is not None and msg["service"] == self.r["counter"]:
                for actor, seq in msg["acked"].items():
                    if actor in self.r["counter_acked"] and isinstance(seq, int):
                        acked = self.r["counter_acked"]
                        acked[actor] = max(acked[actor], seq)
                self.release_counted()
        elif tag == "status":
            msg = self.decode_for_run(key, payload, "status")
            if msg is not None and msg["service"] in self.r["actors"]:
                if msg["state"] == "completed":
                    self.r["final"][msg["service"]] = int(msg["detail"].get("final_seq", 0))
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
        r, cfg = self.r, self.config
        actor = msg["actor"]
        if actor not in r["expected"]:
            self.reject(key, f"unknown actor: {actor}")
            return
        spec = r["spec"]
        check_dims(msg, spec.joint_obs_dim, spec.joint_act_dim)
        n = len(msg["rew"])
        if n != cfg.episode_len:
            raise WireError(f"transitions: a batch is one episode ({cfg.episode_len}), got {n}")
        seq, expected = msg["seq"], r["expected"][actor]
        if seq + n <= expected:
            self.send_ack()  # a resend: tell the actor again where we are
            return
        if seq != expected:
            self.send_ack()
            return  # a gap: the actor resends from our ack
        r["expected"][actor] = seq + n
        r["held"][actor].append(msg)
        self.release_counted()
        self.send_ack()

    def release_counted(self) -> None:
        """Move batches the counter has counted (or all, with no counting) into replay."""
        r, cfg = self.r, self.config
        counting = cfg.explore in ("dis-macb", "cen-macb")
        for actor, held in r["held"].items():
            while held and (
                not counting or held[0]["seq"] + len(held[0]["rew"]) <= r["counter_acked"][actor]
            ):
                self.ingest(held.popleft())

    def ingest(self, msg: dict[str, Any]) -> None:
        r, cfg = self.r, self.config
        r["buffer"].add(msg["obs"], msg["act"], msg["rew"], msg["next_obs"], msg["done"])
        r["ingested"] += len(msg["rew"])
        r["episodes"] += 1
        r["collisions_cum"] += int(msg["collisions"].sum())
        r["lags"].append(r["version"] - msg["policy_version"])
        target = max(0, r["ingested"] - cfg.learning_starts)
        r["boundaries"].append((r["episodes"], target, r["ingested"], r["collisions_cum"]))

    # ------------------------------------------------------------ work
    def tick(self) -> bool:
        if not self.r:
            return False
        r, cfg = self.r, self.config
        learner, buffer = r["learner"], r["buffer"]
        owed = max(0, r["ingested"] - cfg.learning_starts) - learner.updates
        next_boundary = r["boundaries"][0][1] if r["boundaries"] else None
        todo = min(owed, UPDATES_PER_TICK)
        if next_boundary is not None:
            todo = min(todo, max(0, next_boundary - learner.updates))
        spent = r["time"]
        t0 = time.perf_counter()
        batches = [buffer.sample(cfg.batch_size, r["rng"]) for _ in range(todo)]
        spent["sample"] += time.perf_counter() - t0
        r["bonus"].fresh = False
        bonuses = r["bonus"].bonus_for(batches) if batches else []
        if bonuses is None:  # counter silent (restarting?): draw again on the next tick
            batches, bonuses = [], []
        t0 = time.perf_counter()
        evaluating = r["evaluations"].busy
        for batch, bonus in zip(batches, bonuses, strict=True):
            # Counted here for every kind of learner; a tuned one polls the same signal
            # for its tuners and its own count (in its stats(), which take precedence).
            contended = evaluating()
            r["contended_updates"] += contended
            learner.update(
                batch.obs,
                batch.act,
                batch.rew[:, None] + bonus,
                batch.next_obs,
                batch.done,
            )
            r["bonus_means"].append(float(bonus.mean()))
            owed -= 1
        t1 = time.perf_counter()
        spent["update"] += t1 - t0
        self.pass_boundaries()
        spent["publish"] += time.perf_counter() - t1
        now = time.monotonic()
        window_open = owed < MAX_BACKLOG_EPISODES * cfg.episode_len * len(r["actors"])
        if window_open != r["window_open"] or now - r["last_ack"] > 0.5:
            r["window_open"] = window_open
            self.send_ack()
        if now - r["last_stats"] > 1.0:
            r["last_stats"] = now
            self.publish_metrics(self.run_id, self.stats(), source="learner")
        if now - r["last_ckpt"] > CHECKPOINT_EVERY_S:
            self.checkpoint()
        self.maybe_finish()
        return owed > 0 and bool(self.r)

    def pass_boundaries(self) -> None:
        """Publish weights at each episode boundary whose updates are done."""
        r, cfg = self.r, self.config
        while r["boundaries"] and r["learner"].updates >= r["boundaries"][0][1]:
            episode, _, env_steps, collisions = r["boundaries"].popleft()
            is_eval = episode % cfg.eval_every == 0 or episode == cfg.episodes
            self.publish_weights(
                eval_point=episode if is_eval else -1,
                episode=episode,
                env_steps=env_steps,
                collisions=collisions,
            )

    def publish_weights(
        self, eval_point: int, episode: int = 0, env_steps: int = 0, collisions: int = 0
    ) -> None:
        r = self.r
        if episode:  # version 0 is the initial weights; each boundary makes a new one
            r["version"] += 1
        payload = encode(
            "weights",
            self.run_id,
            version=r["version"],
            updates=r["learner"].updates,
            env_steps=env_steps,
            episodes=episode,
            eval_point=eval_point,
            collisions_cum=collisions,
            actors=weights_as_arrays(r["learner"].actor_weights()),
            info={**self.stats(), "counter": self.counter_stats() if eval_point >= 0 else {}},
        )
        if eval_point >= 0:
            r["eval_pub"](payload)
            r["evaluations"].sent(eval_point)
        else:
            r["weights_pub"](payload)

    def counter_stats(self) -> dict[str, Any]:
        """The counter's stats for this run now (table size, count-1 %, counted): from the
        reply to this tick's bonus query when there was one, else by asking the counter."""
        bonus = self.r["bonus"]
        if bonus.tables is not None and bonus.fresh:
            return dict(bonus.tables)
        counter = self.r.get("counter")
        if not counter:
            return {}
        for raw in self.bus.get(keys.k_info("counter", counter), timeout=1.0):
            try:
                return dict(json.loads(raw).get("runs", {}).get(self.run_id, {}))
            except (ValueError, AttributeError, TypeError):
                return {}
        return {}

    def send_ack(self) -> None:
        r = self.r
        r["last_ack"] = time.monotonic()
        window = WINDOW_EPISODES * self.config.episode_len if r["window_open"] else 0
        r["ack_pub"](
            encode("ack", self.run_id, service=self.id, acked=dict(r["expected"]), window=window)
        )

    def stats(self) -> dict[str, Any]:
        r, cfg = self.r, self.config
        updates = r["learner"].updates
        owed_total = max(0, r["ingested"] - cfg.learning_starts)
        wall = time.perf_counter() - r["t0"]
        lat = sorted(r["bonus"].latencies)
        per_update = 1e3 / updates if updates else 0.0
        phases = {**r["time"], "bonus_wait": r["bonus"].wait_s}
        spent = {f"ms_per_update_{k}": v * per_update for k, v in phases.items()}
        spent["ms_per_update_other"] = (wall - sum(phases.values())) * per_update
        return {
            "updates": updates,
            "ingested": r["ingested"],
            "episodes_ingested": r["episodes"],
            "replay_ratio": updates / owed_total if owed_total else 0.0,
            "policy_lag": float(np.mean(r["lags"])) if r["lags"] else 0.0,
            "policy_version": r["version"],
            "wall_s": wall,
            "steps_per_sec": r["ingested"] / wall if wall > 0 else 0.0,
            "updates_per_sec": updates / wall if wall > 0 else 0.0,
            "backlog": owed_total - updates,
            "window_open": r["window_open"],
            "bonus_p50_ms": 1e3 * lat[len(lat) // 2] if lat else 0.0,
            "bonus_p99_ms": 1e3 * lat[int(len(lat) * 0.99)] if lat else 0.0,
            "bonus_wait_ms_per_update": spent["ms_per_update_bonus_wait"],
            "bonus_queries": r["bonus"].queries,
            "bonus_rows_per_query": r["bonus"].rows / max(1, r["bonus"].queries),
            "bonus_failures": r["bonus"].failures,
            "bonus_mean": float(np.mean(r["bonus_means"])) if r["bonus_means"] else 0.0,
            "rejects_total": sum(self.rejects.values()),
            "contended_updates": r["contended_updates"],
            "eval_rows_seen": r["evaluations"].reported_rows,
            **spent,
            **r["learner"].stats(),
        }

    def maybe_finish(self) -> None:
        r, cfg = self.r, self.config
        if set(r["final"]) != set(r["actors"]):
            return
        if any(r["expected"][a] < r["final"][a] for a in r["actors"]):
            return
        if any(r["held"][a] for a in r["actors"]) or r["boundaries"]:
            return
        if r["learner"].updates < max(0, r["ingested"] - cfg.learning_starts):
            return
        run = self.run_id
        self.checkpoint()
        stats = self.stats()
        self.publish_metrics(run, stats, source="learner")
        self.publish_status(run, "completed", **stats)
        self.log.info("run %s completed: %s", run, json.dumps(stats))
        self.r = {}
        self.free(run)

    def on_peer_lost(self, role: str, peer: str) -> None:
        """An actor that dies mid-run fails the run: its transitions cannot come."""
        if role == "actor" and peer in self.r.get("actors", ()) and peer not in self.r["final"]:
            self.fail(f"actor {peer} died before it finished its episodes")

    def fail(self, reason: str) -> None:
        run = self.run_id
        self.log.error("run %s failed: %s", run, reason)
        self.publish_status(run, "failed", reason=reason)
        self.r = {}
        self.free(run)

    def checkpoint(self) -> None:
        """Networks, optimizers and step counters, loadable with weights_only=True."""
        r = self.r
        if not r:
            return
        r["last_ckpt"] = time.monotonic()
        out = self.data_dir / "learner" / self.run_id
        out.mkdir(parents=True, exist_ok=True)
        state = {
            "config": json.dumps(self.config.model_dump(mode="json")),
            "learner": r["learner"].state_dict(),
            "counters": {
                "ingested": r["ingested"],
                "episodes": r["episodes"],
                "updates": r["learner"].updates,
                "expected": dict(r["expected"]),
                "version": r["version"],
            },
        }
        tmp = out / "checkpoint.tmp"
        torch.save(state, tmp)
        tmp.replace(out / "checkpoint.pt")


def make_service(service_id: str, connect: list[str], data_dir: Path) -> LearnerService:
    return LearnerService(service_id, connect, data_dir)
