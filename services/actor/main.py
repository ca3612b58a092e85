"""The actor service: collects training episodes and publishes them, numbered, once each.

An actor of rank r (its place in the run's assignment) steps one environment
seeded from (run seed, "actor", r) and runs its share of the run's episodes. Each
episode goes out as one `transitions` batch stamped with the weights version that
acted. Weights arrive on a callback that only keeps the newest message; the actor
loads it between episodes, so it never works through a backlog of stale weights.

Every batch stays in a resend queue until the learner (and, when counting, the
counter) have acknowledged it, and is resent after a second without progress; the
learner's window of credits and a bound on batches the counter has not acknowledged
hold the actor back when either falls behind or is down (`shared.protocol.Sender`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.common import ServiceBase
from shared import bus as keys
from shared.config import TrainConfig
from shared.networks import JointPolicy
from shared.protocol import Sender
from shared.rollout import Collector, make_collector
from shared.tasks import TaskEnv, make_task_for
from shared.wire import encode

MAX_UNCOUNTED_BATCHES = 8  # episodes in flight that the counter has not acknowledged
RESEND_AFTER_S = 1.0


def episode_share(episodes: int, actors: int, rank: int) -> int:
    """Episodes actor `rank` runs: the run's total split as evenly as possible."""
    return episodes // actors + (1 if rank < episodes % actors else 0)


@dataclass
class ActorRun:
    """Everything an actor holds for the run it serves."""

    rank: int
    env: TaskEnv
    collector: Collector
    policy: JointPolicy
    todo: int  # episodes this actor runs
    sender: Sender  # numbering, unacknowledged batches, resends, credit
    pub: Callable[[bytes], None]
    version: int = -1  # weights version acting now; -1 until the learner's first weights
    done: int = 0
    steps: int = 0
    last_stats: float = 0.0
    t0: float = field(default_factory=time.perf_counter)


class ActorService(ServiceBase):
    role = "actor"
    follows_learner = True

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        torch.set_num_threads(1)
        self._newest: tuple[str, bytes] | None = None  # the newest weights message only
        # Subscribed for the service's lifetime: the learner's first weights may be out
        # before this actor has handled the start message. The slot holds one message.
        self.bus.subscribe(keys.k_weights("*", "*"), self._on_weights)
        self.st: ActorRun | None = None

    def _on_weights(self, key: str, payload: bytes) -> None:
        self._newest = (key, payload)  # overwrite: older versions are never looked at

    # ------------------------------------------------------------ lifecycle
    def on_start(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        actors = list(assign["actors"])
        rank = actors.index(self.id)
        self.listen(keys.k_ack(run, "*"), "ack", run)
        env = make_task_for(config)
        learner, counter = assign.get("learner"), assign.get("counter")
        counting = config.explore in ("dis-macb", "cen-macb")
        self.st = ActorRun(
            rank=rank,
            env=env,
            collector=make_collector(config, env, rank, len(actors)),
            policy=JointPolicy.for_task(env.spec, config.hidden),
            todo=episode_share(config.episodes, len(actors), rank),
            sender=Sender(
                confirm=(learner, counter) if counting else (learner,),
                credit_from=learner,
                bounded=(counter,) if counting else (),
                max_unconfirmed=MAX_UNCOUNTED_BATCHES,
                resend_after_s=RESEND_AFTER_S,
                last_progress=time.monotonic(),
            ),
            pub=self.bus.publisher(keys.k_transitions(run, self.id)),
        )
        self.publish_status(run, "running", rank=rank, episodes=self.st.todo)

    def on_stop(self, run: str, reason: str) -> None:
        self.st = None

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag != "ack":
            return
        msg = self.decode_for_run(key, payload, "ack")
        if msg is None or self.st is None:
            return
        self.st.sender.on_ack(
            msg["service"], msg["acked"].get(self.id), time.monotonic(), window=msg["window"]
        )

    def load_newest_weights(self) -> None:
        newest, st = self._newest, self.st
        if newest is None or st is None:
            return
        key, payload = newest
        if keys.run_of(key) != self.run_id:
            return
        msg = self.decode_for_run(key, payload, "weights")
        if msg is not None and msg["version"] > st.version:
            st.policy.load(msg["actors"])
            st.version = msg["version"]

    # ------------------------------------------------------------ work
    def tick(self) -> bool:
        st = self.st
        if st is None:
            return False
        self.load_newest_weights()
        if st.version < 0:
            return False  # wait for the learner's initial weights
        now = time.monotonic()
        for payload in st.sender.due(now):
            st.pub(payload)
        if now - st.last_stats > 1.0:
            st.last_stats = now
            self.publish_metrics(self.run_id, self.stats())
        if st.done < st.todo:
            if st.sender.can_send(self.config.episode_len):
                self.run_episode()
                return True
            return False
        if st.sender.settled:
            run = self.run_id
            self.publish_metrics(run, self.stats())
            self.publish_status(run, "completed", final_seq=st.sender.seq, **self.stats())
            self.log.info("run %s: %d episodes published", run, st.done)
            self.st = None
            self.free(run)
        return False

    def run_episode(self) -> None:
        st = self.st
        assert st is not None
        collector, policy = st.collector, st.policy
        rows = [collector.step(policy) for _ in range(self.config.episode_len)]
        payload = encode(
            "transitions",
            self.run_id,
            actor=self.id,
            seq=st.sender.seq,
            obs=np.stack([t.obs for t in rows]),
            act=np.stack([t.act for t in rows]),
            rew=np.array([t.rew for t in rows], np.float32),
            next_obs=np.stack([t.next_obs for t in rows]),
            done=np.array([t.done for t in rows], np.float32),
            collisions=np.array([t.collisions for t in rows], np.int32),
            policy_version=st.version,
        )
        st.sender.send(len(rows), payload, time.monotonic())
        st.pub(payload)
        st.done += 1
        st.steps += len(rows)

    def stats(self) -> dict[str, Any]:
        st = self.st
        assert st is not None
        wall = time.perf_counter() - st.t0
        return {
            "rank": st.rank,
            "episodes": st.done,
            "published": st.sender.seq,
            "policy_version": st.version,
            "resends": st.sender.resends,
            "steps_per_sec": st.steps / wall if wall > 0 else 0.0,
            "rejects_total": sum(self.rejects.values()),
        }


def make_service(service_id: str, connect: list[str], data_dir: Path) -> ActorService:
    return ActorService(service_id, connect, data_dir)
