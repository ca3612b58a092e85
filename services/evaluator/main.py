"""The evaluation role: noise-free episodes at every evaluation point, one metric row each.

It listens only to weights the learner marked as evaluation points (so it never
decodes the per-episode weights it does not need) and evaluates every one of them,
in order, with `eval_episodes` episodes run in lockstep. Its row carries the
trainer's metric fields; the learner put the counter's statistics at that boundary
into the weights message.

A point the learner sends again (it saw no row for it) is evaluated once: if its row
is out already, that row is published again. The evaluator's part ends when the
learner completes (the learner waits for every point's row, so points whose weights
were lost, e.g. sent before this service subscribed, come again first). An evaluator
restarted mid-run rejoins the run and evaluates what the learner sends again. Rows go
out in episode order: each point names the earlier ones the learner had no row of when
it was sent, and a point waits (at most ORDER_WAIT_S) until those are evaluated.

A run group's points (docs/architecture.md, "Run groups in the cluster") are evaluated
as one batched rollout once every run of the group has its point (`evaluate_group`:
one act call for every run's worlds per step; run r's result is what `evaluate` gives
it alone). A point only some runs have (an evaluator restarted between rows) waits at
most GROUP_WAIT_S, then goes alone.

It also keeps every row it published for its recent runs (the last `HISTORY_RUNS`)
and answers `macb/run/{run}/history/eval` with them, so a watcher that was away (the
API restarting, say) fills its gaps instead of losing the points published meanwhile.
"""

from __future__ import annotations

import collections
import os
import threading
import time
from collections.abc import Container, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.common import ServiceBase
from shared.config import TrainConfig
from shared.core.networks import JointPolicy
from shared.envs.tasks import TaskEnv, TaskSpec, make_task_for
from shared.envs.vectask import vectorize
from shared.net import bus as keys
from shared.net.messages import History, Weights
from shared.net.wire import encode
from shared.run.factories import build_learner
from shared.run.rollout import EvalResult, derive_seed, evaluate, evaluate_group

HISTORY_RUNS = 64  # runs whose rows are kept for history queries
REPUBLISH_AFTER_S = 5.0  # a row is published again for a resend only this long after
# A point is held back at most this long for an earlier one the learner has not had a
# row of (the learner resends a lost point after 30 s of silence: EVAL_RESEND_S).
ORDER_WAIT_S = 40.0
# A group's point waits this long for the same point of the group's other runs.
GROUP_WAIT_S = 5.0


def earliest_point(
    pending: Iterable[Weights], published: Container[int]
) -> tuple[Weights, list[int]]:
    """The pending weights message of the earliest point, and the earlier points it
    names as unreported that are neither evaluated here nor pending (to wait for)."""
    pending = list(pending)
    msg = min(pending, key=lambda m: m.eval_point)
    here = {m.eval_point for m in pending}
    missing = [
        q for q in msg.unreported if q < msg.eval_point and q not in published and q not in here
    ]
    return msg, missing


class LearnerPolicy:
    """The learner's own `act` on the weights it sent: with `interleave: lockstep` the
    points are `macb train`'s to the bit, and it evaluates with this very function
    (JointPolicy's numpy forward equals it only up to float32 rounding)."""

    def __init__(self, config: TrainConfig, spec: TaskSpec) -> None:
        exact = config.model_copy(update={"learner_lanes": 1})  # acting: no lanes to tune
        self.learner = build_learner(exact, spec)

    def load(self, weights: list[dict[str, Any]]) -> None:
        self.learner.load_actor_weights(
            [{k: torch.as_tensor(np.array(v)) for k, v in sd.items()} for sd in weights]
        )

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.learner.act(obs)


class GroupPolicy:
    """A group's actors in one GroupMADDPG (acting only): each run's weights loaded as
    its points come, one `act` for every run's worlds (the learner's own function, so
    each run's actions are those of `LearnerPolicy` alone, to the bit)."""

    def __init__(self, configs: list[TrainConfig], spec: TaskSpec) -> None:
        from shared.core.learners.group import GroupMADDPG
        from shared.run.factories import agent_dims, learner_spec

        self.learner = GroupMADDPG(
            agent_dims(spec),
            [learner_spec(c) for c in configs],
            precision=configs[0].precision,
            device=configs[0].device,
        )

    def load(self, run: int, weights: list[dict[str, Any]]) -> None:
        self.learner.load_run_actor_weights(
            run, [{k: torch.as_tensor(np.array(v)) for k, v in sd.items()} for sd in weights]
        )

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.learner.act(obs)


@dataclass
class GroupEval:
    """A run group's evaluation: its runs in order, their worlds as one VecTask (run r's
    are r*m .. r*m+m-1: its own evaluation envs) and one policy for all."""

    runs: list[str]
    venv: Any
    policy: GroupPolicy
    waiting_since: float | None = None


@dataclass
class EvaluatorRun:
    """The evaluation environments and the points waiting, for a run served."""

    run: str
    envs: list[TaskEnv]
    policy: JointPolicy | LearnerPolicy
    pending: collections.deque[Weights] = field(default_factory=collections.deque)
    points: int = 0
    published: dict[int, float] = field(default_factory=dict)  # point -> when its row went
    held_since: float | None = None  # the next point waits for an earlier one since then
    t0: float = field(default_factory=time.perf_counter)


class EvaluatorService(ServiceBase):
    role = "evaluator"
    follows_learner = True

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        torch.set_num_threads(1)
        # MACB_EVALUATOR_NICE (default 0): a lower CPU priority for the evaluator, so its
        # bursts disturb the learner's two threads less (no clear gain in paired runs; off
        # by default because a starved evaluator on a saturated machine falls behind and
        # queues weights).
        if nice := int(os.environ.get("MACB_EVALUATOR_NICE", "0")):
            os.nice(nice)
        self.runs: dict[str, EvaluatorRun] = {}  # the run served, or a group's runs
        self.group: GroupEval | None = None
        # run -> (state, rows published); read on Zenoh's thread, hence the lock.
        self.history: collections.OrderedDict[str, tuple[str, list[dict[str, Any]]]] = (
            collections.OrderedDict()
        )
        self._history_lock = threading.Lock()
        self.bus.queryable(keys.k_history("*", "eval"), self._history_reply)

    @property
    def st(self) -> EvaluatorRun | None:
        """The (first) run served."""
        return next(iter(self.runs.values()), None)

    def _history_reply(self, key: str, payload: bytes) -> bytes | None:
        run = keys.run_of(key)
        with self._history_lock:
            entry = self.history.get(run or "")
            if entry is None:
                return None  # not ours: another evaluator may answer
            state, rows = entry[0], list(entry[1])
        return encode(History(run, source="eval", rows=rows, state=state))

    def _remember(self, run: str, state: str, row: dict[str, Any] | None = None) -> None:
        with self._history_lock:
            _, rows = self.history.pop(run, ("running", []))
            if row is not None:
                rows.append(row)
            self.history[run] = (state, rows)
            while len(self.history) > HISTORY_RUNS:
                self.history.popitem(last=False)

    def on_start(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        self.listen(keys.k_weights(run, "eval"), "weights", run)
        envs = [make_task_for(config) for _ in range(min(config.eval_episodes, 10))]
        for j, env in enumerate(envs):
            env.reset(seed=derive_seed(config.seed, "eval", j))
        policy: JointPolicy | LearnerPolicy
        if config.interleave == "lockstep":
            policy = LearnerPolicy(config, envs[0].spec)
        else:
            policy = JointPolicy.for_task(envs[0].spec, config.hidden)
        self.runs[run] = EvaluatorRun(run, envs, policy)
        with self._history_lock:  # a run queued again starts afresh: not the old rows
            self.history.pop(run, None)
        self._remember(run, "running")
        self.publish_status(run, "running")
        group = assign.get("group")
        if not group:
            self.group = None  # (whatever group ended before this run)
        if group and set(group) <= set(self.runs) and config.interleave == "lockstep":
            sts = [self.runs[r] for r in group]
            envs = [env for st in sts for env in st.envs]
            policy = GroupPolicy([self.active[r] for r in group], envs[0].spec)
            self.group = GroupEval(list(group), vectorize(envs), policy)

    def on_stop(self, run: str, reason: str) -> None:
        self._remember(run, "stopped")
        self.runs.pop(run, None)
        if self.group is not None and run in self.group.runs:
            self.group = None  # (its other runs are stopped too, or go on alone)

    def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "weights":
            msg = self.decode_for_run(key, payload, Weights)
            st = self.runs.get(msg.run) if msg is not None else None
            if msg is None or st is None or msg.eval_point < 0:
                return
            point = msg.eval_point
            if any(p.eval_point == point for p in st.pending):
                return  # sent again while we are behind: it is evaluated once
            if point in st.published:  # sent again: its row was lost on the way
                # ... unless the row went out moments ago: then the learner's resend
                # crossed it (it is resent again later if it was lost after all).
                if time.monotonic() - st.published[point] > REPUBLISH_AFTER_S:
                    self._publish_again(st, point)
                return
            st.pending.append(msg)  # new, or sent again because its weights were lost

    def _publish_again(self, st: EvaluatorRun, point: int) -> None:
        """Publish the row of a point evaluated already (the learner did not see it)."""
        with self._history_lock:
            rows = list(self.history.get(st.run, ("", []))[1])
        for row in rows:
            if row["episode"] == point:
                self.publish_metrics(st.run, row, source="eval")
                st.published[point] = time.monotonic()
                return

    def next_point(self, st: EvaluatorRun) -> dict[str, Any] | None:
        """The earliest pending point, unless an earlier one it names as unreported is
        neither evaluated nor here yet (its resend is on the way: after an evaluator
        restart the learner's newest point can arrive before the resends of the ones
        missed); then None, for at most ORDER_WAIT_S, so rows go out in episode order."""
        if not st.pending:
            return None
        msg, missing = earliest_point(st.pending, st.published)
        now = time.monotonic()
        if missing:
            if st.held_since is None:
                st.held_since = now
            if now - st.held_since < ORDER_WAIT_S:
                return None
            self.log.warning(
                "run %s: point %d evaluated without %s (not resent within %.0f s)",
                st.run, msg.eval_point, missing, ORDER_WAIT_S,
            )  # fmt: skip
        st.held_since = None
        st.pending.remove(msg)
        return msg

    def tick(self) -> bool:
        """One point of one run, or a group's point of all its runs; True while more
        wait."""
        if self.group is not None and self.group_tick(self.group):
            return any(s.pending for s in self.runs.values())
        if self.group is not None:
            return False
        for st in list(self.runs.values()):
            msg = self.next_point(st)
            if msg is not None:
                self.evaluate_point(st, msg)
                return any(s.pending for s in self.runs.values())
        return False

    def group_tick(self, g: GroupEval) -> bool:
        """The group's earliest point, evaluated for every run at once when every run
        has it (and nothing earlier to wait for); after GROUP_WAIT_S without that, a
        run's point alone. True if a point was evaluated."""
        sts = [self.runs[r] for r in g.runs if r in self.runs]
        heads = [(st, *earliest_point(st.pending, st.published)) for st in sts if st.pending]
        if not heads:
            g.waiting_since = None
            return False
        point = min(msg.eval_point for _, msg, _ in heads)
        ready = [(st, msg) for st, msg, missing in heads if msg.eval_point == point]
        if len(sts) == len(g.runs) and len(ready) == len(sts) and not any(m for *_, m in heads):
            g.waiting_since = None
            for r, (st, msg) in enumerate(ready):
                st.pending.remove(msg)
                g.policy.load(r, msg.actors)
            cfg = self.active[g.runs[0]]
            results = evaluate_group(g.policy, g.venv, len(g.runs), cfg.eval_episodes)
            for (st, msg), ev in zip(ready, results):
                self.publish_row(st, msg, ev)
            return True
        now = time.monotonic()
        if g.waiting_since is None:
            g.waiting_since = now
        if now - g.waiting_since < GROUP_WAIT_S:
            return False
        for st in sts:  # the point goes alone (same worlds, same streams)
            msg = self.next_point(st)
            if msg is not None:
                g.waiting_since = None
                self.evaluate_point(st, msg)
                return True
        return False

    def evaluate_point(self, st: EvaluatorRun, msg: Weights) -> None:
        cfg = self.active[st.run]
        st.policy.load(msg.actors)
        self.publish_row(st, msg, evaluate(st.policy, st.envs, cfg.eval_episodes))

    def publish_row(self, st: EvaluatorRun, msg: Weights, ev: EvalResult) -> None:
        run = st.run
        info = msg.stats
        counts = info.get("counter") or {}  # the counter's stats at this boundary
        bonus = info.get("bonus") or {}  # what the bonus did since the last point
        row = {
            "episode": msg.eval_point,
            "env_steps": msg.env_steps,
            "success_rate": ev.success_rate,
            "eval_return": ev.eval_return,
            "collisions_cum": msg.collisions_cum,
            "count1_pct": counts.get("count1_pct", 0.0),
            "table_size": counts.get("table_size", 0),
            "counted_transitions": counts.get("counted_transitions", 0),
            "bonus_mean": bonus.get("bonus_mean", 0.0),
            "bonus_std": bonus.get("bonus_std", 0.0),
            "sampled_count1_pct": bonus.get("sampled_count1_pct", 0.0),
            "steps_per_sec": info.get("steps_per_sec", 0.0),
            "train_steps_per_sec": info.get("steps_per_sec", 0.0),
            "updates": msg.updates,
            "wall_s": info.get("wall_s", 0.0),
            "replay_ratio": info.get("replay_ratio", 0.0),
            "policy_lag": info.get("policy_lag", 0.0),
            "policy_version": msg.version,
        }
        self._remember(run, "running", row)
        self.publish_metrics(run, row, source="eval")
        st.published[msg.eval_point] = time.monotonic()
        st.points += 1
        # The last point is not the end: points lost on the way (weights published
        # before this service had subscribed, a router restart) come again from the
        # learner, which completes only once it has every point's row.

    def on_learner_completed(self, run: str) -> None:
        """The learner has every point's row: this run's evaluation is over."""
        st = self.runs.get(run)
        if st is None:
            return
        # (none left: the learner waited for their rows)
        for msg in sorted(st.pending, key=lambda m: m.eval_point):
            self.evaluate_point(st, msg)
        st.pending.clear()
        self._remember(run, "completed")
        self.publish_status(run, "completed", points=st.points)
        self.log.info("run %s: %d evaluation points", run, st.points)
        del self.runs[run]
        self.free(run)
        if self.group is not None and not any(r in self.runs for r in self.group.runs):
            self.group = None  # the group is over: the next run is evaluated alone


def make_service(service_id: str, connect: list[str], data_dir: Path) -> EvaluatorService:
    return EvaluatorService(service_id, connect, data_dir)
