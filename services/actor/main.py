"""The actor service: collects training episodes and publishes them, numbered, once each.

An actor of rank r (its place in the run's assignment) steps one environment
seeded from (run seed, "actor", r) and runs its share of the run's episodes. Each
episode goes out as one `transitions` batch stamped with the weights version that
acted. Weights arrive on a callback that only keeps the newest message; the actor
loads it between episodes, so it never works through a backlog of stale weights.

Every batch stays in a resend queue until the learner (and, when counting, the
counter) have acknowledged it; unacknowledged batches are resent after a second
without progress. The learner's window of credits, and a bound on batches the
counter has not acknowledged, hold the actor back when either falls behind or is
down.
"""

from __future__ import annotations

import collections
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.common import ServiceBase
from shared import bus as keys
from shared.config import TrainConfig
from shared.networks import JointPolicy
from shared.rollout import Collector, derive_seed
from shared.tasks import make_task
from shared.wire import encode

MAX_UNCOUNTED_BATCHES = 8  # episodes in flight that the counter has not acknowledged
RESEND_AFTER_S = 1.0


def episode_share(episodes: int, actors: int, rank: int) -> int:
    """Episodes actor `rank` runs: the run's total split as evenly as possible."""
    return episodes // actors + (1 if rank < episodes % actors else 0)


def make_policy(config: TrainConfig, env) -> JointPolicy:
    spec = env.spec
    return JointPolicy(
        spec.obs_dims,
        [a.act_low for a in spec.agents],
        [a.act_high for a in spec.agents],
        config.hidden,
    )


class ActorService(ServiceBase):
    role = "actor"

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        torch.set_num_threads(1)
        self._newest: tuple[str, bytes] | None = None  # the newest weights message only
        # Subscribed for the service's lifetime: the learner's first weights may be out
        # before this actor has handled the start message. The slot holds one message.
        self.bus.subscribe(keys.k_weights("*", "*"), self._on_weights)
        self.s: dict[str, Any] = {}

    def _on_weights(self, key: str, payload: bytes) -> None:
        self._newest = (key, payload)  # overwrite: older versions are never looked at

    # ------------------------------------------------------------ lifecycle
    def on_start(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        actors = list(assign["actors"])
        rank = actors.index(self.id)
        self.listen(keys.k_ack(run, "*"), "ack", run)
        env = make_task(config.task, config.agents, config.reward, config.episode_len)
        seed = derive_seed(config.seed, "actor", rank)
        self.s = {
            "rank": rank,
            "env": env,
            "collector": Collector(env, config.noise_sigma, seed, config.time_limit_terminal),
            "policy": make_policy(config, env),
            "version": -1,
            "todo": episode_share(config.episodes, len(actors), rank),
            "done": 0,
            "seq": 0,
            "unacked": collections.deque(),  # (seq, n, payload)
            "learner": assign.get("learner"),
            "counter": assign.get("counter"),
            "counting": config.explore in ("dis-macb", "cen-macb"),
            "acked_learner": 0,
            "acked_counter": 0,
            "window": 0,
            "last_progress": time.monotonic(),
            "resends": 0,
            "pub": self.bus.publisher(keys.k_transitions(run, self.id)),
            "t0": time.perf_counter(),
            "steps": 0,
            "last_stats": 0.0,
        }
        self.publish_status(run, "running", rank=rank, episodes=self.s["todo"])

    def on_stop(self, run: str, reason: str) -> None:
        self.s = {}

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag != "ack":
            return
        msg = self.decode_for_run(key, payload, "ack")
        if msg is None:
            return
        s = self.s
        seq = msg["acked"].get(self.id)
        if not isinstance(seq, int):
            return
        if msg["service"] == s["learner"]:
            if seq > s["acked_learner"]:
                s["last_progress"] = time.monotonic()
            s["acked_learner"] = max(s["acked_learner"], seq)
            s["window"] = int(msg["window"])
        elif msg["service"] == s["counter"]:
            if seq > s["acked_counter"]:
                s["last_progress"] = time.monotonic()
            s["acked_counter"] = max(s["acked_counter"], seq)
        fully = min(s["acked_learner"], s["acked_counter"] if s["counting"] else 1 << 62)
        while s["unacked"] and s["unacked"][0][0] + s["unacked"][0][1] <= fully:
            s["unacked"].popleft()

    def load_newest_weights(self) -> None:
        newest = self._newest
        if newest is None:
            return
        key, payload = newest
        if keys.run_of(key) != self.run_id:
            return
        msg = self.decode_for_run(key, payload, "weights")
        if msg is not None and msg["version"] > self.s["version"]:
            self.s["policy"].load(msg["actors"])
            self.s["version"] = msg["version"]

    # ------------------------------------------------------------ work
    def can_send(self) -> bool:
        s, n = self.s, self.config.episode_len
        if s["seq"] + n > s["acked_learner"] + s["window"]:
            return False  # no credit: the learner is behind
        uncounted = (s["seq"] - s["acked_counter"]) // n if s["counting"] else 0
        return uncounted < MAX_UNCOUNTED_BATCHES

    def tick(self) -> bool:
        if not self.s:
            return False
        s = self.s
        self.load_newest_weights()
        if s["version"] < 0:
            return False  # wait for the learner's initial weights
        now = time.monotonic()
        if s["unacked"] and now - s["last_progress"] > RESEND_AFTER_S:
            for _, _, payload in s["unacked"]:
                s["pub"](payload)
                s["resends"] += 1
            s["last_progress"] = now
        if now - s["last_stats"] > 1.0:
            s["last_stats"] = now
            self.publish_metrics(self.run_id, self.stats())
        if s["done"] < s["todo"]:
            if self.can_send():
                self.run_episode()
                return True
            return False
        if not s["unacked"]:
            run = self.run_id
            self.publish_metrics(run, self.stats())
            self.publish_status(run, "completed", final_seq=s["seq"], **self.stats())
            self.log.info("run %s: %d episodes published", run, s["done"])
            self.s = {}
            self.free(run)
        return False

    def run_episode(self) -> None:
        s = self.s
        collector, policy = s["collector"], s["policy"]
        rows = [collector.step(policy) for _ in range(self.config.episode_len)]
        payload = encode(
            "transitions",
            self.run_id,
            actor=self.id,
            seq=s["seq"],
            obs=np.stack([t.obs for t in rows]),
            act=np.stack([t.act for t in rows]),
            rew=np.array([t.rew for t in rows], np.float32),
            next_obs=np.stack([t.next_obs for t in rows]),
            done=np.array([t.done for t in rows], np.float32),
            collisions=np.array([t.collisions for t in rows], np.int32),
            policy_version=s["version"],
        )
        if not s["unacked"]:
            s["last_progress"] = time.monotonic()
        s["unacked"].append((s["seq"], len(rows), payload))
        s["pub"](payload)
        s["seq"] += len(rows)
        s["done"] += 1
        s["steps"] += len(rows)

    def stats(self) -> dict[str, Any]:
        s = self.s
        wall = time.perf_counter() - s["t0"]
        return {
            "rank": s["rank"],
            "episodes": s["done"],
            "published": s["seq"],
            "policy_version": s["version"],
            "resends": s["resends"],
            "steps_per_sec": s["steps"] / wall if wall > 0 else 0.0,
            "rejects_total": sum(self.rejects.values()),
        }


def make_service(service_id: str, connect: list[str], data_dir: Path) -> ActorService:
    return ActorService(service_id, connect, data_dir)
