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
most GROUP_WAIT_S, then goes alone. A run alone is served as a group of one, by the
same code: its points go as soon as they are next.

It also keeps every row it published for its recent runs (the last `HISTORY_RUNS`)
and answers `macb/run/{run}/history/eval` with them, so a watcher that was away (the
API restarting, say) fills its gaps instead of losing the points published meanwhile.

This module is the shell: the bus, the timers and the dispatch. The parts hold no bus:
`points.py` (which point next, a resend's fate, a group's point together, the row),
`history.py` (the rows kept for history queries) and `policies.py` (the learner's own
`act` for lockstep runs and groups).
"""

from __future__ import annotations

import itertools
import os
import time
from pathlib import Path

import torch

from services.common import ServiceBase
from services.evaluator.history import RowHistory
from services.evaluator.points import (
    ORDER_WAIT_S,
    EvaluatorRun,
    GroupEval,
    earliest_point,  # noqa: F401 (the ordering rule, read here by tests)
    eval_row,
    take_next,
)
from services.runs import LearnerProcesses
from shared.config import TrainConfig
from shared.metrics import early_stop_reason
from shared.net import bus as keys
from shared.net.messages import Assignment, History, Weights, learner_of
from shared.net.wire import encode
from shared.run.rollout import EvalResult
from shared.settings import settings


class EvaluatorService(ServiceBase):
    role = "evaluator"
    follows_learner = True
    # The clock of its waits (the order and group waits): a test's own, not the process's.
    clock = staticmethod(time.monotonic)

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        torch.set_num_threads(1)
        # MACB_EVALUATOR_NICE (default 0): a lower CPU priority for the evaluator, so its
        # bursts disturb the learner's two threads less (no clear gain in paired runs; off
        # by default because a starved evaluator on a saturated machine falls behind and
        # queues weights).
        if nice := settings().evaluator_nice:
            os.nice(nice)
        self.runs: dict[str, EvaluatorRun] = {}  # the run served, or a group's runs
        self.group: GroupEval | None = None  # those runs as one (a run alone: of one)
        self.history = RowHistory()
        self._retired: set[str] = set()  # the group's runs ended by their rule (a restart)
        # The learner processes whose points it took, per run: a late point of an ended
        # attempt's learner (paused, it had not yet taken its stop) is not the new one's.
        self.took_points = LearnerProcesses()
        self.answer(keys.k_history("*", "eval"), self._history_reply)

    def _history_reply(self, key: str, payload: bytes) -> bytes | None:
        run = keys.run_of(key)
        entry = None if run is None else self.history.answer(run)
        if run is None or entry is None:
            return None  # not ours: another evaluator may answer
        state, rows, attempt = entry
        if attempt is None:  # (rows kept since a restart: the attempt rejoined)
            attempt = self.served.attempts.get(run)
        return encode(History(run, source="eval", rows=rows, state=state, attempt=attempt))

    def on_start(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        self.took_points.begin([run])
        self.listen(keys.k_weights(run, "eval"), "weights", run)
        self.runs[run] = EvaluatorRun.open(run, config)
        self.history.start(run, self.served.attempts.get(run))
        self.publish_status(run, "running")
        # The runs served as one: a run alone is a group of one; a start replaces
        # whatever group ended before it.
        self.group = GroupEval.open(list(assign.group or [run]), self.runs, self.active)
        self.group.ended |= self._retired & set(self.group.runs)

    def on_resume_retired(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        """A run of the group its rule ended before this process restarted: no point of
        it is waited for."""
        self._retired.add(run)

    def on_stop(self, run: str, reason: str) -> None:
        self.history.remember(run, "stopped")
        self.end(run)

    def end(self, run: str) -> None:
        """The run's evaluation is over (completed or stopped): its group goes with its
        last run, alike for a run alone and a group's runs."""
        self.runs.pop(run, None)
        if self.group is not None and not any(r in self.runs for r in self.group.runs):
            self.group = None
        elif self.group is not None:  # (its rule ended it: the others' points go on together)
            self.group.ended.add(run)

    def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag != "weights":
            return
        msg = self.decode_for_run(key, payload, Weights)
        st = self.runs.get(msg.run) if msg is not None else None
        if msg is None or st is None or msg.eval_point < 0 or not self._from_its_learner(msg):
            return
        if why := st.refusal(msg):
            self.reject(key, why)
            return
        self.took_points.took(msg.run, msg.incarnation)
        if st.receive(msg, self.clock()):  # evaluated: the learner did not see its row
            row = self.history.row(st.run, msg.eval_point)
            if row is not None:
                self.publish_metrics(st.run, row, source="eval")
                st.published[msg.eval_point] = self.clock()

    def _from_its_learner(self, msg: Weights) -> bool:
        """A point from the run's assigned learner (an incarnation naming no learner is
        an older learner's: taken), and from none that served an ended attempt of it."""
        if self.took_points.of_ended_attempt(msg.run, msg.incarnation):
            return False
        if not self.of_attempt(msg.run, msg.attempt):
            return False
        learner = learner_of(msg.incarnation)
        return learner is None or self.assign is None or learner == self.assign.learner

    def next_point(self, st: EvaluatorRun) -> Weights | None:
        """The earliest pending point to evaluate now (`points.take_next`), or None
        while it waits for an earlier one, at most ORDER_WAIT_S."""
        msg, given_up = take_next(st, self.clock())
        if msg is not None and given_up:
            self.log.warning(
                "run %s: point %d evaluated without %s (not resent within %.0f s)",
                st.run, msg.eval_point, given_up, ORDER_WAIT_S,
            )  # fmt: skip
        return msg

    def tick(self) -> bool:
        """The earliest point of the runs served, evaluated for every run at once when
        every run has it (and nothing earlier to wait for; a run alone: when it has
        one); after GROUP_WAIT_S without that, one run's point alone. True while more
        points wait."""
        g = self.group
        sts = [self.runs[r] for r in g.runs if r in self.runs] if g is not None else []
        if g is None or not any(st.pending for st in sts):
            if g is not None:
                g.waiting_since = None
            return False
        ready = g.take_together(sts)
        if ready:
            results = g.evaluate(ready)
        elif not g.waited_out(self.clock()):
            return False
        else:  # one run's point alone (its own worlds, the same streams)
            alone = ((st, m) for st in sts if (m := self.next_point(st)) is not None)
            ready = list(itertools.islice(alone, 1))  # (the runs after it are not asked)
            if not ready:
                return False
            results = [st.evaluate(msg) for st, msg in ready]
        g.waiting_since = None
        for (st, msg), ev in zip(ready, results):
            self.publish_row(st, msg, ev)
        return any(s.pending for s in self.runs.values())

    def publish_row(self, st: EvaluatorRun, msg: Weights, ev: EvalResult) -> None:
        cfg = st.config
        row = eval_row(msg, ev, cfg)
        if cfg is not None and cfg.early_stop is not None:  # read on the rows so far
            entry = self.history.get(st.run)
            kept = {r["episode"]: r for r in (entry[1] if entry else [])}  # (once each)
            earlier = [kept[e] for e in sorted(kept) if e < msg.eval_point]
            if why := early_stop_reason(cfg.early_stop, [*earlier, row]):
                row["stop_reason"] = why  # the learner ends the run at this point
        self.history.remember(st.run, "running", row)
        self.publish_metrics(st.run, row, source="eval")
        st.row_out(msg.eval_point, self.clock())
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
            self.publish_row(st, msg, st.evaluate(msg))
        st.pending.clear()
        self.history.remember(run, "completed")
        self.publish_status(run, "completed", points=st.points)
        self.log.info("run %s: %d evaluation points", run, st.points)
        self.end(run)
        if self.group is not None and st.config is not None and st.config.early_stop is not None:
            self.retire(run)  # its rule ended it; the group goes on (noted for a restart)
        else:
            self.free(run)


def make_service(service_id: str, connect: list[str], data_dir: Path) -> EvaluatorService:
    return EvaluatorService(service_id, connect, data_dir)
