"""Which evaluation point is evaluated next, and the row it gives.

A point may come twice (the learner resends what it has no row of), out of order (a
restarted evaluator gets the newest point before the resends of those it missed), or
for only some runs of a group (a run alone is a group of one). The rules deciding what
to take, hold, publish again or evaluate together are here on the clock they are
given, so they are tested without a bus; the service evaluates and publishes.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Container, Iterable
from dataclasses import dataclass, field
from typing import Any

from services.evaluator.policies import GroupPolicy, LearnerPolicy
from shared.config import TrainConfig
from shared.core.networks import JointPolicy, Layout, weights_error
from shared.envs.tasks import TaskEnv, make_task_for
from shared.envs.vectask import vectorize
from shared.net.messages import Weights
from shared.net.stats import LearnerStats, learner_stats_error
from shared.run.rollout import EvalResult, derive_seed, evaluate, evaluate_group

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


@dataclass
class EvaluatorRun:
    """The evaluation environments and the points waiting, for a run served."""

    run: str
    envs: list[TaskEnv]
    policy: JointPolicy | LearnerPolicy
    layout: Layout  # the actors' names and shapes a point's weights must have
    pending: collections.deque[Weights] = field(default_factory=collections.deque)
    points: int = 0
    published: dict[int, float] = field(default_factory=dict)  # point -> when its row went
    held_since: float | None = None  # the next point waits for an earlier one since then
    t0: float = field(default_factory=time.perf_counter)
    eval_episodes: int = 0
    config: TrainConfig | None = None  # (the beta its rows record)

    @classmethod
    def open(cls, run: str, config: TrainConfig) -> EvaluatorRun:
        """Its own evaluation worlds (seeded from the run's seed) and the policy it acts
        with: the learner's own in lockstep, JointPolicy's forward otherwise."""
        envs = [make_task_for(config) for _ in range(min(config.eval_episodes, 10))]
        for j, env in enumerate(envs):
            env.reset(seed=derive_seed(config.seed, "eval", j))
        policy: JointPolicy | LearnerPolicy
        joint = JointPolicy.for_task(envs[0].spec, config.hidden)  # (the learner sends its layout)
        policy = LearnerPolicy(config, envs[0].spec) if config.interleave == "lockstep" else joint
        return cls(
            run, envs, policy, joint.layout, eval_episodes=config.eval_episodes, config=config
        )

    def refusal(self, msg: Weights) -> str | None:
        """Why a point's weights cannot be evaluated and its row made, or None: actors
        not of the run's layout, or stats a row cannot read. Checked as they arrive, so
        the evaluation loop never meets them (it raised there, ending the process)."""
        why = weights_error(msg.actors, self.layout)
        if why is None and (bad := learner_stats_error(msg.stats)) is not None:
            why = f"stats: {bad}"
        return None if why is None else f"weights: {why}"

    def evaluate(self, msg: Weights) -> EvalResult:
        """A point on the run's own worlds."""
        self.policy.load(msg.actors)
        return evaluate(self.policy, self.envs, self.eval_episodes)

    def receive(self, msg: Weights, now: float) -> bool:
        """A point's weights arrive: kept to evaluate unless already pending or evaluated
        (a resend). True if its row is to be published again: evaluated, and the row went
        out more than REPUBLISH_AFTER_S ago (a resend within that crossed the row, and
        comes again later if the row was lost after all)."""
        point = msg.eval_point
        if any(p.eval_point == point for p in self.pending):
            return False  # sent again while we are behind: it is evaluated once
        if point in self.published:  # sent again: its row was lost on the way
            return now - self.published[point] > REPUBLISH_AFTER_S
        self.pending.append(msg)  # new, or sent again because its weights were lost
        return False

    def row_out(self, point: int, now: float) -> None:
        self.published[point] = now
        self.points += 1


def take_next(st: EvaluatorRun, now: float) -> tuple[Weights | None, list[int]]:
    """The earliest pending point, taken, unless an earlier one it names as unreported
    is neither evaluated nor here yet (its resend is on the way: after an evaluator
    restart the learner's newest point can arrive before the resends of the ones
    missed); then None, for at most ORDER_WAIT_S, so rows go out in episode order.
    Also returns the points given up waiting for (taken without them)."""
    if not st.pending:
        return None, []
    msg, missing = earliest_point(st.pending, st.published)
    if missing:
        if st.held_since is None:
            st.held_since = now
        if now - st.held_since < ORDER_WAIT_S:
            return None, []
    st.held_since = None
    st.pending.remove(msg)
    return msg, missing


@dataclass
class GroupEval:
    """The runs served as one, in order: a lockstep group's, or a run alone (a group of
    one). A lockstep group's worlds, once every run has its start, are one VecTask (run
    r's are r*m .. r*m+m-1: its own evaluation envs) with one policy for all; without
    them (a run alone, a group still forming) each run is evaluated on its own worlds."""

    runs: list[str]
    venv: Any = None
    policy: GroupPolicy | None = None
    waiting_since: float | None = None
    # Runs the learner completed while others of the group go on (`early_stop`): no
    # point of theirs is waited for; their worlds still step in the batched rollout.
    ended: set[str] = field(default_factory=set)

    @classmethod
    def open(
        cls, runs: list[str], sts: dict[str, EvaluatorRun], configs: dict[str, TrainConfig]
    ) -> GroupEval:
        """The group `runs` (of which `sts` have their start so far)."""
        together = len(runs) > 1 and all(r in sts for r in runs)
        if not together or configs[runs[0]].interleave != "lockstep":
            return cls(list(runs))
        envs = [env for r in runs for env in sts[r].envs]
        return cls(
            list(runs), vectorize(envs), GroupPolicy([configs[r] for r in runs], envs[0].spec)
        )

    def take_together(self, sts: list[EvaluatorRun]) -> list[tuple[EvaluatorRun, Weights]]:
        """The group's earliest point, taken from every run, when every run of the group
        has it and none waits for an earlier one; else nothing is taken ([])."""
        heads = [(st, *earliest_point(st.pending, st.published)) for st in sts if st.pending]
        if not heads:
            return []
        point = min(msg.eval_point for _, msg, _ in heads)
        ready = [(st, msg) for st, msg, missing in heads if msg.eval_point == point]
        going = len(self.runs) - len(self.ended)
        if len(sts) < going or len(ready) < len(sts) or any(m for *_, m in heads):
            return []
        for st, msg in ready:
            st.pending.remove(msg)
            st.held_since = None
        return ready

    def evaluate(self, ready: list[tuple[EvaluatorRun, Weights]]) -> list[EvalResult]:
        """The point `take_together` took: one act call per step for every run when the
        group's worlds are one (run r's result is what its own worlds give it alone),
        else on its own worlds."""
        if self.policy is None:
            return [st.evaluate(msg) for st, msg in ready]
        at = [self.runs.index(st.run) for st, _ in ready]  # (an ended run's entry: unread)
        for r, (_, msg) in zip(at, ready):
            self.policy.load(r, msg.actors)
        episodes = ready[0][0].eval_episodes
        results = evaluate_group(self.policy, self.venv, len(self.runs), episodes)
        return [results[r] for r in at]

    def waited_out(self, now: float) -> bool:
        """A point not every run has yet has waited GROUP_WAIT_S (the clock starts now
        if it was not running): it goes alone. A group of one waits for no one."""
        if self.waiting_since is None:
            self.waiting_since = now
        return len(self.runs) == 1 or now - self.waiting_since >= GROUP_WAIT_S


def eval_row(msg: Weights, ev: EvalResult, config: TrainConfig | None = None) -> dict[str, Any]:
    """A point's metric row: the trainer's fields, the evaluation's and the learner's
    statistics at that point (the counter's and the bonus's ride in its weights), and
    the columns of the options its `config` sets: `beta`, the one in force at the
    point's last transition (`beta_at`), and `stop_reason` (the service sets it where
    the run's `early_stop` rule holds)."""
    info = LearnerStats.from_wire(msg.stats)
    options: dict[str, Any] = {}
    if config is not None and config.beta_schedule is not None:
        options["beta"] = config.beta_at(msg.env_steps)
    if config is not None and config.early_stop is not None:
        options["stop_reason"] = None
    counts = info.tables  # the counter's stats at this boundary
    return {
        "episode": msg.eval_point,
        "env_steps": msg.env_steps,
        "success_rate": ev.success_rate,
        "eval_return": ev.eval_return,
        "collisions_cum": msg.collisions_cum,
        "count1_pct": counts.count1_pct,
        "table_size": counts.table_size,
        "counted_transitions": counts.counted_transitions,
        # what the bonus did since the last point
        "bonus_mean": info.bonus_stat("bonus_mean"),
        "bonus_std": info.bonus_stat("bonus_std"),
        "sampled_count1_pct": info.bonus_stat("sampled_count1_pct"),
        "steps_per_sec": info.steps_per_sec,
        "train_steps_per_sec": info.steps_per_sec,
        "updates": msg.updates,
        "wall_s": info.wall_s,
        "replay_ratio": info.replay_ratio,
        "policy_lag": info.policy_lag,
        "policy_version": msg.version,
        **options,
    }
